"""The report of a sweep's results store, whichever sweep wrote it (``sc3 sweep bench`` or ``sc3 sweep episodes``):
every number comes from :func:`compute` (one call, JSON-serialisable), and :func:`render` only formats it (markdown
and HTML tables; for a bench store plots and side-by-side videos, ``report_figures.py``). The numbers of a store of
held-out episodes are ``report_episodes.py``'s; those of a bench store ``report_bench.py``'s, in words and tables
``report_bench_render.py``'s:

    from sc3_jax.evaluation.report import compute
    tables = compute("runs/sweep")            # the exact numbers in report.md / report.json
"""
from __future__ import annotations

import json
from pathlib import Path

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import report_bench, report_bench_render, report_episodes, report_html
from sc3_jax.evaluation.merged import open_store


def compute(results, taus=None, draws: int = 2000, seed: int = 0, scene=None, real=None) -> dict:
    """Every number of the report of the store(s) at ``results``, whichever sweep wrote it: a sweep of held-out
    episodes (``report_episodes.compute``; ``real``: its real-outcome sources, None: the sweep's own) or a bench
    sweep (``report_bench.bench``); ``scene``: the benchmark's object measure (objects kept). ``taus``: other
    candidate thresholds, read from the stored U_chunk (no new rollouts)."""
    roots = [results] if isinstance(results, (str, Path)) else list(results)
    if len(roots) == 1 and report_episodes.is_store(roots[0]):
        return report_episodes.compute(roots[0], real, draws, seed, taus, scene)
    if real:
        raise UserError("--real applies to a sweep of held-out episodes (sc3 sweep episodes); a bench sweep's real "
                        "rollouts are in its store")
    return report_bench.bench(results, taus, draws, seed, scene)


def _parts(t: dict) -> dict:
    """What a report page shows, for either kind of sweep: title, headline lines, warnings, the answer's tables,
    the detail tables, the method paragraph and the facts of the run."""
    if t.get("kind") == report_episodes.KIND:
        cfg, e = t["config"], report_episodes
        return {"title": "Sweep report: held-out episodes", "headlines": e.verdict(t), "warnings": t["warnings"],
                "answer": e.tables(t)[:1], "details": e.tables(t)[1:], "method": e.METHOD,
                "facts": [f"World model {Path(cfg['world_model']).name}, initial conditions "
                          f"{Path(cfg['initial_conditions']).name}; rollouts {t['rollouts']}"]}
    b = report_bench_render
    warn = b.incomplete(t)
    return {"title": "Sweep report: bench", "headlines": [b.headline(t)],
            "warnings": ([warn] if warn else []) + t.get("warnings", []),
            "answer": b.ranking_tables(t), "details": b.tables(t), "method": b.method(t),
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
    title, header, rows = next(x for x in report_bench_render.tables(t) if x[0].startswith("Faithfulness, end to end"))
    return [report_html.markdown_table(title, header, rows)] + report_bench_render.verdict(t) + t.get("warnings", [])


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
            report_bench_render.figures(open_store(results), t, stage, videos)
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
