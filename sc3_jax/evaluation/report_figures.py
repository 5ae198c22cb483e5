"""The pictures of a bench sweep's report: imagined against real success, U_chunk per chunk, a real-over-imagined
filmstrip and a side-by-side video per policy. Each writes the path it is given (``report.render`` passes one inside
its staging directory)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sc3_jax.evaluation import calibrate
from sc3_jax.evaluation.report_html import ci
from sc3_jax.evaluation.results import ResultsStore, paired_frames, seed_blocks


def scatter(t: dict, path: Path, headline_split: str) -> None:
    """Imagined against real success per (policy, criterion), each point named with its 95% interval bars, the
    diagonal, and the policy-blind guess (grey x) the evaluator has to beat; one split: its r is
    ``headline_split``'s (the report's headline)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    splits = list(t["ranking"])
    fig, axes = plt.subplots(1, len(splits), figsize=(5.6 * len(splits), 5.2), squeeze=False)
    colors = {c: f"C{k}" for k, c in enumerate(t["criteria"])}  # matplotlib's cycle: tab:blue, tab:orange, ...
    for ax, split in zip(axes[0], splits):
        r = t["ranking"][split]
        for k, c in enumerate(t["criteria"]):
            pts = [(x["real"][c], x["rates"][c], x["policy"]) for x in r["policies"]]
            xs, ys = [p[0]["value"] for p in pts], [p[1]["value"] for p in pts]
            err = lambda cells, v: np.abs(np.array([[q["lo"] for q in cells], [q["hi"] for q in cells]]) - v)  # noqa
            ax.errorbar(xs, ys, xerr=err([p[0] for p in pts], xs), yerr=err([p[1] for p in pts], ys), fmt="o",
                        ms=4, color=colors[c], ecolor=colors[c], elinewidth=0.7, alpha=0.85, label=c)
            guess = float(np.nanmean(xs)) if xs else np.nan
            ax.plot(xs, [guess] * len(xs), "x", color="grey", ms=5, label="policy-blind guess" if k == 0 else None)
            for x, y, (_, _, name) in zip(xs, ys, pts):
                ax.annotate(name, (x, y), fontsize=6, xytext=(3, 2), textcoords="offset points")
        ax.plot([0, 1], [0, 1], "k:", lw=1)
        f = t["faithfulness"]["physics"].get(r["mode"], {}).get("splits", {}).get(split if len(splits) > 1 else
                                                                                 headline_split, {})
        ax.set(xlabel="real success rate (simulator)", ylabel=f"imagined success rate ({r['mode']})",
               xlim=(-0.03, 1.03), ylim=(-0.03, 1.03),
               title=f"{split.replace('_', ' ')}: r {ci(f.get('pearson'))}")
        ax.title.set_fontsize(9)
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def u_plot(store: ResultsStore, t: dict, path: Path) -> None:
    """U_chunk over the chunks of a rollout, every policy: its median over the evaluation conditions, the band
    between the quartiles, the candidate taus."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    units = t["tau"]["units"]
    seeds = set(seed_blocks(t["config"])["evaluation"])
    by: dict[str, list] = {}
    for r in store.records():
        if r["mode"] == "online" and r["seed"] in seeds:
            by.setdefault(r["policy"], []).append(r["u"] if units == "normalised" else r["u_raw"])
    fig, ax = plt.subplots(figsize=(7.5, 4.0))
    for policy, us in sorted(by.items()):
        n = min(len(u) for u in us)
        u = np.array([x[:n] for x in us])
        q1, med, q3 = np.quantile(u, [0.25, 0.5, 0.75], axis=0)
        line, = ax.plot(np.arange(n), med, marker=".", label=policy)
        ax.fill_between(np.arange(n), q1, q3, color=line.get_color(), alpha=0.12)
    for tau in (calibrate.parse_tau(x) for x in t["config"]["taus"]):
        if math.isfinite(tau):
            ax.axhline(tau, ls="--", lw=1, color="grey")
            ax.text(0, tau, f"tau={tau}", fontsize=7, va="bottom")
    ax.set(xlabel="chunk", ylabel=f"U_chunk ({units})", yscale="log")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def filmstrip(store: ResultsStore, policy: str, seed: int, path: Path, frames: int = 6) -> bool:
    """A picture of one condition: per view a row of real frames over a row of imagined ones, at the same moments;
    False if the store does not keep both rollouts' frames."""
    got = paired_frames(store, policy, seed)
    if got is None:
        return False
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    real, online, at, _ = got
    pick = np.unique(np.linspace(0, online.shape[1] - 1, frames).round().astype(int))
    rows, labels = [], []
    for v in range(online.shape[0]):
        rows += [np.concatenate(list(real[v, at[pick]]), 1), np.concatenate(list(online[v, pick]), 1)]
        labels += [f"real, view {v}", f"imagined, view {v}"]
    grid = np.concatenate(rows, 0)
    h = real.shape[2]
    fig, ax = plt.subplots(figsize=(min(12, 1.6 * len(pick)), 0.45 + 1.6 * len(rows) * h / real.shape[3]))
    ax.imshow(grid)
    ax.set_yticks([h * (i + 0.5) for i in range(len(rows))], labels, fontsize=7)
    ax.set_xticks([real.shape[3] * (i + 0.5) for i in range(len(pick))], [f"step {int(x)}" for x in at[pick]],
                  fontsize=7)
    ax.set_title(f"{policy}, condition {seed}: real over imagined", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


def side_by_side(store: ResultsStore, policy: str, seed: int, path: Path, fps: float) -> bool:
    """mp4 of real | online (| offline where kept) as columns, views as rows, played at ``fps`` (the model's rollout
    frame rate, the online frames'); False if the store does not keep the real and online frames."""
    from sc3_jax.core.video import write_mp4
    got = paired_frames(store, policy, seed)
    if got is None:
        return False
    real, online, at, offline = got
    n = online.shape[1]
    cols = [real[:, at], online] + ([offline[:, :n]] if offline is not None else [])
    write_mp4(path, np.concatenate(list(np.concatenate(cols, axis=3)), axis=1), fps)  # views stacked vertically
    return True
