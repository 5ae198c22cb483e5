"""Reports from a sweep's results store: every number comes from :func:`compute` (one call, JSON-serialisable), and
:func:`render` only formats it (markdown + HTML tables, plots, side-by-side videos).

    from sc3_jax.evaluate.report import compute
    tables = compute("runs/sweep")            # the exact numbers in report.md / report.json

Tables (the paper's): main (split x offline/online: Pearson r, MMRV), early termination (tau: termination rate, r,
MMRV per split), outcome reproduction per category (offline/online), offline PSNR per view, and the perception
scorer's agreement with physics on the real rollouts. Rates are compared only over (policy, seed) cases present in
every mode being compared, so a partial sweep still reports consistent numbers (``cases`` says how many).
"""
from __future__ import annotations

import html
import json
import math
from pathlib import Path

import numpy as np

from sc3_jax.evaluate import metrics
from sc3_jax.evaluate.sweep import ResultsStore

SPLIT_ORDER = ("in_distribution", "out_of_distribution", metrics.OVERALL)


def _parse_tau(t) -> float:
    return math.inf if str(t) in ("inf", "Infinity") else float(t)


def _object_rows(rec: dict, objects: list[dict]) -> list[dict]:
    return [{"policy": rec["policy"], "split": rec["split"], "episode": rec["seed"], "object": o["object"],
             **{c: bool(o[c]) for c in metrics.CRITERIA}} for o in objects]


def _cut(rec: dict, tau: float, units: str) -> int:
    """Index into objects_by_cut for threshold tau: the first chunk with U > tau (its frames are dropped)."""
    u = np.asarray(rec["u"] if units == "normalised" else rec["u_raw"])
    above = np.flatnonzero(u > tau)
    return int(above[0]) if len(above) else len(u)


def _rates(rows: list[dict]) -> dict:
    return {s: {f"{p}/{c}": v for (p, c), v in r.items()} for s, r in metrics.success_rates_by_split(rows).items()}


def _faith(ev_rows, real_rows) -> dict:
    return _faith_rates(metrics.success_rates_by_split(ev_rows), metrics.success_rates_by_split(real_rows))


def _faith_rates(ev, re) -> dict:
    splits = [s for s in SPLIT_ORDER if s in re]
    out = metrics.faithfulness(ev, re, splits)
    return {s: out[s] for s in SPLIT_ORDER if s in out}


def _policy_blind(real_rates: dict) -> dict:
    """An evaluator that knows each criterion's *average* real success rate in a split but nothing about the
    policies: every policy gets the same rates. Pooling criteria gives it a high r (language is easy for everyone,
    placing hard), which is the floor a world model's r has to be read against."""
    return {s: {(p, c): float(np.mean([v for (_, cc), v in r.items() if cc == c])) for (p, c) in r}
            for s, r in real_rates.items()}


def _per_criterion(ev_rows, real_rows) -> dict:
    """r and MMRV over the policies within one criterion (all splits pooled): free of the between-criteria spread
    that inflates the pooled r."""
    ev, re = metrics.success_rates(ev_rows), metrics.success_rates(real_rows)
    out = {}
    for c in metrics.CRITERIA:
        keys = [k for k in re if k[1] == c]
        s, r = [ev[k] for k in keys], [re[k] for k in keys]
        out[c] = {"pearson": metrics.pearson(s, r), "mmrv": metrics.mmrv(s, r), "n": len(keys)}
    return out


def compute(results: str | Path, taus=None, tau_units: str | None = None) -> dict:
    """All report numbers from the results store at ``results`` (see the module docstring). ``taus`` /
    ``tau_units`` override the sweep's termination thresholds: every online record stores U_chunk and the outcomes
    of every cut, so any threshold is evaluated without rolling out again."""
    store = ResultsStore(results)
    cfg = json.loads((store.root / "sweep.json").read_text())
    if taus is not None:
        cfg["taus"] = [str(float(t)) for t in taus]
    if tau_units is not None:
        if tau_units not in ("normalised", "raw"):
            raise ValueError(f"tau_units {tau_units!r}: 'normalised' or 'raw'")
        cfg["tau_units"] = tau_units
    recs = store.records()
    by_mode = {m: {(r["policy"], r["seed"]): r for r in recs if r["mode"] == m} for m in ("real", "offline", "online")}
    real = by_mode["real"]
    if not real:
        raise ValueError(f"{results}: no real rollouts yet: faithfulness needs the simulator's ground truth")
    out: dict = {"config": cfg, "counts": {m: len(v) for m, v in by_mode.items()},
                 "policies": sorted({(r["policy"], r["split"]) for r in real.values()}, key=lambda x: (x[1], x[0]))}
    # ground truth and the scorer's agreement with it
    real_rows = [row for r in real.values() for row in _object_rows(r, r["objects"])]
    out["rates"] = {"real": _rates(real_rows)}
    from sc3_jax.evaluate.scorers import agreement
    out["scorer_agreement"] = agreement([r["perception"] for r in real.values()], [r["objects"] for r in real.values()])
    out["rates"]["real_perception"] = _rates([row for r in real.values() for row in _object_rows(r, r["perception"])])
    out["main"], out["reproduction"], out["cases"] = {}, {}, {}
    for mode in ("offline", "online"):
        cases = sorted(set(by_mode[mode]) & set(real))
        if not cases:
            continue
        ev_rows = [row for k in cases for row in _object_rows(by_mode[mode][k], by_mode[mode][k]["objects"])]
        re_rows = [row for k in cases for row in _object_rows(real[k], real[k]["objects"])]
        out["cases"][mode] = len(cases)
        out["rates"][mode] = _rates(ev_rows)
        out["main"][mode] = _faith(ev_rows, re_rows)
        out.setdefault("per_criterion", {})[mode] = _per_criterion(ev_rows, re_rows)
        counts = metrics.reproduction_counts(metrics.outcome_categories(re_rows), metrics.outcome_categories(ev_rows))
        out["reproduction"][mode] = {c: {"rate": m / n, "reproduced": m, "cases": n} for c, (m, n) in counts.items()}
    real_rates = metrics.success_rates_by_split(real_rows)
    out["baselines"] = {"policy_blind": _faith_rates(_policy_blind(real_rates), real_rates)}
    if "online" in out["cases"]:
        cases = sorted(set(by_mode["online"]) & set(real))
        re_rows = [row for k in cases for row in _object_rows(real[k], real[k]["objects"])]
        out["termination"] = []
        for tau in (_parse_tau(t) for t in cfg["taus"]):
            cut = {k: _cut(by_mode["online"][k], tau, cfg["tau_units"]) for k in cases}
            ev_rows = [row for k in cases
                       for row in _object_rows(by_mode["online"][k], by_mode["online"][k]["objects_by_cut"][cut[k]])]
            faith = _faith(ev_rows, re_rows)
            term = {}
            for split in SPLIT_ORDER:
                ks = [k for k in cases if split == metrics.OVERALL or real[k]["split"] == split]
                if ks:
                    term[split] = float(np.mean([cut[k] < by_mode["online"][k]["num_chunks"] for k in ks]))
            out["termination"].append({"tau": str(tau), "termination_rate": term, "faithfulness": faith,
                                       "mean_chunks_kept": float(np.mean(list(cut.values())))})
        u = np.concatenate([by_mode["online"][k]["u" if cfg["tau_units"] == "normalised" else "u_raw"]
                            for k in cases])
        out["u_quantiles"] = {q: float(np.quantile(u, float(q))) for q in ("0.1", "0.5", "0.9")}
    if by_mode["offline"]:
        pv = np.array([r["psnr_view"] for r in by_mode["offline"].values()])
        out["psnr"] = {"per_view": [float(x) for x in np.nanmean(pv, 0)], "mean": float(np.nanmean(pv)),
                       "rollouts": len(pv)}
    return out


# ================================================================================================================
# Rendering
# ================================================================================================================
def _fmt(x, nd=3):
    if x is None:
        return "-"
    if isinstance(x, float):
        return "nan" if math.isnan(x) else f"{x:.{nd}f}"
    return str(x)


def tables(t: dict) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, header, rows) of every table in the report, formatted from :func:`compute`'s output."""
    out = []
    modes = [m for m in ("offline", "online") if m in t["main"]]
    rows = []
    for split in SPLIT_ORDER:
        row = [split]
        for m in modes:
            f = t["main"][m].get(split)
            row += [_fmt(f["pearson"]), _fmt(f["mmrv"])] if f else ["-", "-"]
        rows.append(row)
    for split in SPLIT_ORDER:
        f = t["baselines"]["policy_blind"].get(split)
        rows[SPLIT_ORDER.index(split)] += [_fmt(f["pearson"]), _fmt(f["mmrv"])] if f else ["-", "-"]
    out.append(("Main table: faithfulness of imagined success rates (Pearson r higher is better, MMRV lower; "
                "'policy-blind' = every policy gets its split's mean real rate per criterion, the floor to read "
                "r against)",
                ["split"] + [f"{m} {k}" for m in modes for k in ("r", "MMRV")] + ["policy-blind r", "policy-blind MMRV"],
                rows))
    if t.get("per_criterion"):
        out.append(("Per criterion, over policies (both splits)", ["criterion"] +
                    [f"{m} {k}" for m in modes for k in ("r", "MMRV")],
                    [[c] + [_fmt(t["per_criterion"][m][c][k]) for m in modes for k in ("pearson", "mmrv")]
                     for c in metrics.CRITERIA]))
    if "termination" in t:
        rows = []
        for e in t["termination"]:
            row = [e["tau"]]
            for split in SPLIT_ORDER:
                f = e["faithfulness"].get(split)
                row += [_fmt(e["termination_rate"].get(split)), _fmt(f["pearson"]) if f else "-",
                        _fmt(f["mmrv"]) if f else "-"]
            rows.append(row)
        out.append((f"Early termination (online, U_chunk in {t['config']['tau_units']} action units)",
                    ["tau"] + [f"{s} {k}" for s in SPLIT_ORDER for k in ("term. rate", "r", "MMRV")], rows))
    rows = [[c] + [(f"{_fmt(t['reproduction'][m][c]['rate'], 2)} ({t['reproduction'][m][c]['reproduced']}/"
                    f"{t['reproduction'][m][c]['cases']})") if c in t["reproduction"].get(m, {}) else "-"
                   for m in modes] for c in metrics.CATEGORIES]
    out.append(("Outcome reproduction per real outcome category (objects)", ["category"] + modes, rows))
    if "psnr" in t:
        out.append(("Offline PSNR (dB, mean over valid frames)", ["view " + str(i) for i in
                                                                 range(len(t["psnr"]["per_view"]))] + ["mean"],
                    [[_fmt(x, 2) for x in t["psnr"]["per_view"]] + [_fmt(t["psnr"]["mean"], 2)]]))
    a = t["scorer_agreement"]
    out.append(("Perception scorer vs physics on real rollouts (agreement per criterion)",
                list(metrics.CRITERIA) + ["outcome", "objects"],
                [[_fmt(a[c]) for c in metrics.CRITERIA] + [_fmt(a["outcome"]), str(a["n_objects"])]]))
    rows = []
    for policy, split in t["policies"]:
        row = [policy, split]
        for m in ("real", "offline", "online"):
            r = t["rates"].get(m, {}).get(split, {})
            row.append(" / ".join(_fmt(r.get(f"{policy}/{c}"), 2) for c in metrics.CRITERIA))
        rows.append(row)
    out.append(("Success rates per policy (language / lifting / placing, cumulative)",
                ["policy", "split", "real", "offline", "online"], rows))
    return out


def markdown(t: dict) -> str:
    parts = [f"# Sweep report\n\nResults: `{t['config']['out']}`; rollouts: {t['counts']}; compared cases: "
             f"{t['cases']}. Recompute every number with `sc3_jax.evaluate.report.compute(RESULTS)`.\n"]
    for title, header, rows in tables(t):
        parts.append(f"## {title}\n\n| " + " | ".join(header) + " |\n|" + "---|" * len(header) + "\n" +
                     "".join("| " + " | ".join(r) + " |\n" for r in rows))
    return "\n".join(parts)


def _html(t: dict, images: list[str], videos: list[str]) -> str:
    body = [f"<h1>Sweep report</h1><p>rollouts: {html.escape(str(t['counts']))}</p>"]
    for title, header, rows in tables(t):
        body.append(f"<h2>{html.escape(title)}</h2><table border=1 cellpadding=4><tr>" +
                    "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>" +
                    "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows) +
                    "</table>")
    body += [f'<h2>{html.escape(Path(i).stem)}</h2><img src="{i}" width=640>' for i in images]
    body += [f'<p><a href="{v}">{html.escape(v)}</a></p>' for v in videos]
    return "<html><body style='font-family:sans-serif'>" + "".join(body) + "</body></html>"


def scatter(t: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    modes = [m for m in ("offline", "online") if m in t["rates"]]
    fig, axes = plt.subplots(1, max(len(modes), 1), figsize=(5 * max(len(modes), 1), 4.6), squeeze=False)
    for ax, mode in zip(axes[0], modes):
        for split, marker in (("in_distribution", "o"), ("out_of_distribution", "^")):
            re, ev = t["rates"]["real"].get(split, {}), t["rates"][mode].get(split, {})
            keys = [k for k in ev if k in re]
            for crit, color in zip(metrics.CRITERIA, ("tab:blue", "tab:orange", "tab:green")):
                ks = [k for k in keys if k.endswith("/" + crit)]
                ax.scatter([re[k] for k in ks], [ev[k] for k in ks], marker=marker, color=color,
                           label=f"{split[:3]} {crit}")
        f = t["main"][mode].get(metrics.OVERALL, {})
        ax.plot([0, 1], [0, 1], "k:", lw=1)
        ax.set(xlabel="real (simulator) success rate", ylabel=f"{mode} (world model) success rate",
               title=f"{mode}: r={_fmt(f.get('pearson'))} MMRV={_fmt(f.get('mmrv'))}", xlim=(-0.03, 1.03),
               ylim=(-0.03, 1.03))
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def u_plot(store: ResultsStore, t: dict, path: Path, examples: int = 4) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    units = t["config"]["tau_units"]
    recs = [r for r in store.records() if r["mode"] == "online"][:examples]
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    for r in recs:
        ax.plot(r["u"] if units == "normalised" else r["u_raw"], marker=".", label=f"{r['policy']} {r['seed']}")
    for tau in (_parse_tau(x) for x in t["config"]["taus"]):
        if math.isfinite(tau):
            ax.axhline(tau, ls="--", lw=1, color="grey")
            ax.text(0, tau, f"tau={tau}", fontsize=7, va="bottom")
    ax.set(xlabel="chunk", ylabel=f"U_chunk ({units})", yscale="log", title="U_chunk per chunk (online)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def side_by_side(store: ResultsStore, policy: str, seed: int, path: Path, fps: int = 10) -> bool:
    """mp4 of real | offline | online (columns) x views (rows) at the model's frame rate; False if not all exist."""
    from sc3_jax.sim.evaluate import write_mp4
    ids = {m: f"{policy}/{seed}_{m}" for m in ("real", "offline", "online")}
    if not all(store.array_path(i).exists() for i in ids.values()):
        return False
    arr = {m: store.load_arrays(i)["frames"] for m, i in ids.items()}
    n = arr["online"].shape[1]  # imagined frames: the initial one, then every model step
    stride = next(r for r in store.records() if r["id"] == ids["online"])["stride"]
    real = arr["real"][:, np.minimum(np.arange(n) * stride, arr["real"].shape[1] - 1)]
    grid = np.concatenate([real, arr["offline"][:, :n], arr["online"][:, :n]], axis=3)  # [V, n, H, 3W, 3]
    write_mp4(path, np.concatenate(list(grid), axis=1), fps)  # views stacked vertically
    return True


def render(results: str | Path, out: str | Path, videos: int = 3, taus=None, tau_units: str | None = None) -> Path:
    """Write report.md, report.html, report.json, plots and example videos to ``out``; returns report.md."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    store = ResultsStore(results)
    t = compute(results, taus, tau_units)
    (out / "report.json").write_text(json.dumps(t, indent=1))
    images = []
    if t["main"]:
        scatter(t, out / "correlation.png")
        images.append("correlation.png")
    if "termination" in t:
        u_plot(store, t, out / "u_chunk.png")
        images.append("u_chunk.png")
    vids = []
    for policy, _ in t["policies"]:
        if len(vids) >= videos:
            break
        seed = t["config"]["seed0"]
        name = f"{policy}_{seed}.mp4"
        if side_by_side(store, policy, seed, out / name):
            vids.append(name)
    md = markdown(t)
    md += "".join(f"\n![{i}]({i})\n" for i in images)
    if vids:
        md += "\n## Real | offline | online (rows: views)\n\n" + "".join(f"* [{v}]({v})\n" for v in vids)
    (out / "report.md").write_text(md)
    (out / "report.html").write_text(_html(t, images, vids))
    return out / "report.md"
