"""Faithfulness against training compute: several world-model checkpoints, each swept online against one real set,
as one table and one plot (``sc3 curve SPEC``).

A curve is a small JSON file (e.g. ``docs/compute_curve.json``)::

    {"title": "...", "points": [
      {"label": "CPU step 2880", "store": "~/sc3-runs/curve/cpu_2880", "steps": 2880, "batch": 12,
       "device": "2-core CPU", "hours": 1.8},
      ...]}

An optional ``"baseline": "LABEL"`` adds each point's paired difference to that point (r and MMRV on the same
resampled conditions): the test for "did more compute help" and for an ablation table (points = the full recipe
and its ablations at one budget, baseline = the full recipe).

``steps`` x ``batch`` is the training windows a checkpoint has seen (the x axis: comparable across devices);
``device`` and ``hours`` say what that cost where it ran (from the training log, stated by whoever trained it).
Every faithfulness number comes from the stores (``report.compute``): r and MMRV of the online rollouts at tau = inf
against the real rollouts scored by physics, with the paired bootstrap intervals, per split, plus the policy-blind
floor and the noise ceiling. The points must share their real rollouts (``sc3 sweep bench --real-from``), which is checked:
a curve whose floor moves between points would compare checkpoints on different tests.
"""
from __future__ import annotations

from pathlib import Path

from sc3_jax.core import atomic
from sc3_jax.evaluation import intervals, report, report_bench
from sc3_jax.evaluation.report_html import ci
from sc3_jax.measures.metrics import OVERALL
from sc3_jax.evaluation.results import ResultsStore, criteria_order, seed_blocks, split_order

FIELDS = ("label", "store", "steps", "batch", "device", "hours")


def read_spec(path: str | Path) -> dict:
    """The curve spec at ``path``, checked (every point has every field; ``store`` may start with ``~``)."""
    spec = atomic.read_json(path, "fix the curve spec (a JSON file, see sc3_jax/evaluation/curve.py)")
    points = spec.get("points") or []
    if not points:
        raise ValueError(f"{path}: no points")
    for i, p in enumerate(points):
        missing = [f for f in FIELDS if f not in p]
        if missing:
            raise ValueError(f"{path}: point {i} ({p.get('label', '?')}) lacks {missing}")
        bad = [f for f, kind in (("steps", int), ("batch", int), ("hours", (int, float)))
               if not isinstance(p[f], kind) or isinstance(p[f], bool) or p[f] < 0]
        if bad:
            raise ValueError(f"{path}: point {i} ({p['label']}): {bad} must be non-negative numbers "
                             "(steps and batch integers)")
        p["store"] = str(Path(p["store"]).expanduser())
    if "baseline" in spec and spec["baseline"] not in [p["label"] for p in points]:
        raise ValueError(f"{path}: baseline {spec['baseline']!r} is not the label of a point")
    return spec


def _real_set(store: str) -> dict:
    """What the floor and the ceiling are computed from: the protocol's evaluation and ceiling seeds and the physics
    outcomes of the real rollouts on them."""
    st = ResultsStore(store)
    blocks = seed_blocks(st.config())
    seeds = set(blocks["evaluation"]) | set(blocks["ceiling"])
    return {"blocks": {k: blocks[k] for k in ("evaluation", "ceiling")},
            "objects": {r["id"]: r["objects"] for r in st.records() if r["mode"] == "real" and r["seed"] in seeds}}


def _grids(store: str):
    """(split of each policy, real grid, online grid) on the evaluation seeds, policies in the report's order."""
    st = ResultsStore(store)
    seeds = seed_blocks(st.config())["evaluation"]
    recs = [r for r in st.records() if r["seed"] in set(seeds)]
    by = {m: {(r["policy"], r["seed"]): r for r in recs if r["mode"] == m} for m in ("real", "online")}
    policies = report_bench.policy_order(by["real"].values(), split_order(st.config(), recs))
    names = [p for p, _ in policies]
    criteria = criteria_order(st.config(), by["real"].values())
    grid = lambda m: intervals.grid(by[m], names, seeds, criteria)  # noqa: E731
    return [s for _, s in policies], grid("real"), grid("online")


def compute(spec: dict, draws: int = 2000) -> dict:
    """Every number of the curve (JSON-serialisable): per point its compute and its online rows per split."""
    points, first = [], spec["points"][0]["store"]
    real = _real_set(first)
    for p in spec["points"]:
        other = _real_set(p["store"])
        if other != real:
            ids = sorted(set(real["objects"]) ^ set(other["objects"]) or
                         {i for i in real["objects"] if real["objects"][i] != other["objects"][i]})
            why = "other evaluation or ceiling seeds" if other["blocks"] != real["blocks"] else f"e.g. {ids[:3]}"
            raise ValueError(f"{p['store']}: its real rollouts differ from {first}'s ({why}); sweep every point "
                             "against one real set (sc3 sweep bench --real-from)")
        t = report.compute(p["store"], draws=draws)
        if not points:  # a curve's columns are per split, never the pooled one
            _SPLITS = list(dict.fromkeys(s for _, s in t["policies"]))
            rows = t["faithfulness"]["physics"]
            floor = {s: rows["policy_blind"]["splits"].get(s) for s in _SPLITS}
            ceiling = {s: rows["ceiling"]["splits"].get(s) for s in _SPLITS}
        online = t["faithfulness"]["physics"].get("online")
        if online is None:
            raise ValueError(f"{p['store']}: no online rollouts on the evaluation seeds")
        points.append({**p, "windows": p["steps"] * p["batch"], "cases": t["cases"]["online"],
                       "gates_failed": None if t["diagnose"]["gates"] is None else
                       [g["gate"] for g in t["diagnose"]["gates"] if g.get("pass") is False],
                       "online": {s: online["splits"].get(s) for s in _SPLITS},
                       "vs_floor": {s: online["vs_floor"].get(s) for s in _SPLITS},
                       "per_criterion": online.get("per_criterion", {})})
    if "baseline" in spec:  # seed 0: the same resamples as every report's intervals
        grids = {p["label"]: _grids(p["store"]) for p in points}
        split_of, real_grid, base = grids[spec["baseline"]]
        for p in points:
            p["vs_baseline"] = intervals.versus(real_grid, grids[p["label"]][2], base, split_of, draws, 0)
    return {"title": spec.get("title", "Faithfulness against training compute"), "points": points,
            "floor": floor, "ceiling": ceiling, "draws": draws, "baseline": spec.get("baseline"), "splits": _SPLITS}


def markdown(c: dict) -> str:
    _SPLITS = c["splits"]
    head = ["checkpoint", "device, hours", "training windows", "online rollouts", "gates failed"]
    head += [f"{s.replace('_', ' ')} {k}" for s in _SPLITS for k in ("r", "MMRV")]
    rows = []
    for p in c["points"]:
        cells = [p["label"], f"{p['device']}, {p['hours']:g} h", f"{p['windows']:,}", str(p["cases"]),
                 str(len(p["gates_failed"])) if p["gates_failed"] is not None else "-"]
        rows.append(cells + [ci((p["online"][s] or {}).get(k)) for s in _SPLITS for k in ("pearson", "mmrv")])
    for name, row in (("policy-blind (floor)", c["floor"]), ("noise ceiling", c["ceiling"])):
        rows.append([name, "", "", "", ""] + [ci((row[s] or {}).get(k)) for s in _SPLITS
                                              for k in ("pearson", "mmrv")])
    lines = [f"# {c['title']}", "",
             f"Online (tau = inf) against real rollouts scored by physics; value [95% paired bootstrap interval over "
             f"initial conditions, {c['draws']} draws].", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    head = ["checkpoint"] + [f"{s.replace('_', ' ')} {k} - floor" for s in _SPLITS for k in ("r", "MMRV")]
    lines += ["", "Better than a guess? The paired difference to the policy-blind floor on the same resampled "
              "conditions (r > 0 and MMRV < 0 favour the checkpoint):", "",
              "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join([p["label"]] + [ci((p["vs_floor"][s] or {}).get(k)) for s in _SPLITS
                                                for k in ("pearson", "mmrv")]) + " |" for p in c["points"]]
    if c.get("baseline"):
        # here the pooled split too: "better than the baseline overall" is a question a curve's user asks
        pooled = [*_SPLITS, OVERALL]
        head = ["checkpoint"] + [f"{s.replace('_', ' ')} {k} - baseline" for s in pooled for k in ("r", "MMRV")]
        lines += ["", f"Paired difference to the baseline, {c['baseline']}, on the same resampled conditions (r > 0 "
                  "and MMRV < 0 favour the checkpoint):", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join([p["label"]] + [ci(p["vs_baseline"].get(s, {}).get(k)) for s in pooled
                                                    for k in ("pearson", "mmrv")]) + " |"
                  for p in c["points"] if p["label"] != c["baseline"]]
    return "\n".join(lines) + "\n"


def plot(c: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    xs = [p["windows"] for p in c["points"]]
    markers = {d: m for d, m in zip(dict.fromkeys(p["device"] for p in c["points"]), "os^Dv")}
    for ax, key, name in zip(axes, ("pearson", "mmrv"), ("Pearson r (higher is better)", "MMRV (lower is better)")):
        for split, color, dx in (("in_distribution", "tab:blue", 0.95), ("out_of_distribution", "tab:orange", 1.05)):
            cells = [(x * dx, (p["online"][split] or {}).get(key), p) for x, p in zip(xs, c["points"])]
            cells = [(x, v, p) for x, v, p in cells if v is not None]
            for x, v, p in cells:
                ax.errorbar([x], [v["value"]], yerr=[[v["value"] - v["lo"]], [v["hi"] - v["value"]]],
                            fmt=markers.get(p["device"], "o"), color=color, capsize=3)
            floor = c["floor"][split]
            if floor and floor.get(key):
                f = floor[key]
                ax.axhspan(f["lo"], f["hi"], color=color, alpha=0.12)
                ax.axhline(f["value"], color=color, ls=":", lw=1, label=f"{split.replace('_', ' ')} (band: floor)")
        devices = ", ".join(f"{m}: {d}" for d, m in markers.items())
        ax.set(xscale="log", xlim=(min(xs) / 2, max(xs) * 2), xlabel=f"training windows seen ({devices})",
               title=name)
        ax.set_xticks(sorted(set(xs)), [f"{x / 1000:.3g}k" for x in sorted(set(xs))])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.legend(fontsize=7)
    fig.suptitle(c["title"], fontsize=10)
    fig.tight_layout()
    with atomic.replacing(path) as tmp:  # the format from the target's suffix, not the temporary's
        fig.savefig(tmp, dpi=110, format=Path(path).suffix[1:] or "png")
    plt.close(fig)


def render(spec_path: str | Path, out: str | Path, draws: int = 2000) -> Path:
    """Write curve.json, curve.md and curve.png to ``out``; returns curve.md. The three are staged and moved into
    ``out`` together once all exist (curve.md last), so a failure or a kill leaves the previous curve as it was."""
    out = Path(out)
    c = compute(read_spec(spec_path), draws)
    with atomic.staged(out, last=("curve.md",)) as stage:
        atomic.write_json(stage / "curve.json", c)
        plot(c, stage / "curve.png")
        atomic.write_text(stage / "curve.md", markdown(c) + "\n![curve](curve.png)\n")
    return out / "curve.md"
