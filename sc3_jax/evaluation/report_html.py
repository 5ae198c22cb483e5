"""The HTML page of a report, for both sweeps (the simulator's and the simulator-free one): the answer first (one
verdict sentence, the ranking), then the pictures, then the method in one paragraph, then every detail table folded.

A results store is something people hand each other: every value it puts into the page (policy names, warnings,
table cells, file names) is escaped here, attributes included, and an image or link names a file of the report's
own directory only, so a store cannot put script or a foreign address into the page. The stylesheet is inline: the
page needs no network and prints as it reads.
"""
from __future__ import annotations

import html
import math
import re
from urllib.parse import quote

STYLE = ("body{font-family:sans-serif;max-width:1100px;margin:1em auto;padding:0 1em;color:#222}"
         "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:2px 6px;text-align:left}"
         "th{background:#eee}.verdict{font-size:1.15em;border-left:4px solid #36c;padding:.3em .8em}"
         ".warn{color:#a40}details{margin:.4em 0}summary{cursor:pointer;font-weight:bold}"
         "figure{margin:.8em 0}figcaption{font-size:.9em;color:#555}img{max-width:100%}"
         "@media print{details{display:block}}")

Table = tuple[str, list[str], list[list[str]]]  # (title, header, rows); the title's first phrase is its heading
UNDEFINED = "n/a"  # a statistic undefined at these rates (said in the report's method paragraph)


def fmt(x, nd: int = 3) -> str:
    """A report cell: a float to ``nd`` decimals, nan as UNDEFINED, None as '-'."""
    if x is None:
        return "-"
    if isinstance(x, float):
        return UNDEFINED if math.isnan(x) else f"{x:.{nd}f}"
    return str(x)


def ci(cell: dict | None, nd: int = 3) -> str:
    """value [lo, hi] of a bootstrap summary ({"value", "lo", "hi"})."""
    if cell is None:
        return "-"
    if not math.isfinite(cell["value"]):
        return UNDEFINED
    return f"{fmt(cell['value'], nd)} [{fmt(cell['lo'], nd)}, {fmt(cell['hi'], nd)}]"


def kept_table(p: dict, what: str) -> tuple[str, list[str], list[list[str]]]:
    """The "objects kept" table of a ``permanence.summary`` (both sweeps' reports): per time, every view's value."""
    cols = list(next(iter(p.values()))["kept"])
    return (f"Objects kept (object permanence), {what}: the benchmark's measure of its objects in the imagined "
            "frames over that in the real ones at the same time, summed over the conditions whose frames the store "
            "keeps; 95% bootstrap over conditions. 1: the objects stay; toward 0: they fade.",
            ["time", "rollouts"] + cols,
            [[label, str(e["rollouts"])] + [ci(e["kept"][c]) for c in cols] for label, e in p.items()])


def markdown_table(title: str, header: list[str], rows: list[list[str]]) -> str:
    return (f"## {title}\n\n| " + " | ".join(header) + " |\n|" + "---|" * len(header) + "\n" +
            "".join("| " + " | ".join(r) + " |\n" for r in rows))


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _src(name: str) -> str:
    """A file of the report's directory as a relative address: never a scheme, an absolute path or '..'."""
    return quote(name.replace("/", "_").lstrip("."), safe="")


def heading(title: str) -> tuple[str, str]:
    """(short heading, the rest) of a table title: split after its first '.', '?' or ':' (none: all heading)."""
    m = re.match(r"(.+?[.?:])\s+(.+)", title, re.S)
    return (m[1].rstrip(".:"), m[2]) if m else (title.rstrip("."), "")


def table(header: list[str], rows: list[list[str]], id_: str = "") -> str:
    return (f"<table{f' id={_e(id_)}' if id_ else ''}><tr>" + "".join(f"<th>{_e(h)}</th>" for h in header) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{_e(c)}</td>" for c in r) + "</tr>" for r in rows) + "</table>")


def page(title: str, verdict: list[str], ranking: list[Table], figures: list[tuple[str, str]] = (),
         videos: list[str] = (), method: str = "", details: list[Table] = (), warnings: list[str] = (),
         facts: list[str] = ()) -> str:
    """The page: ``verdict`` sentences, the ``ranking`` tables, ``figures`` (file name, caption) and ``videos`` (file
    names in the report's directory), the ``method`` paragraph, ``details`` tables folded, ``facts`` (what was read)
    at the end. Every image marks its load (``data-loaded``) or failure (``data-broken``), so a browser test sees each one."""
    body = [f"<h1>{_e(title)}</h1>"]
    body += [f"<p class=verdict id=verdict>{_e(v)}</p>" for v in verdict[:1]] + [f"<p>{_e(v)}</p>" for v in verdict[1:]]
    body += [f"<p class=warn><b>{_e(w)}</b></p>" for w in warnings]
    for i, (t, header, rows) in enumerate(ranking):
        head, note = heading(t)
        body.append(f"<h2>{_e(head)}</h2>" + (f"<p>{_e(note)}</p>" if note else "") +
                    table(header, rows, "ranking" if i == 0 else ""))
    for name, caption in figures:
        body.append(f'<figure><img src="{_src(name)}" alt="{_e(caption)}" '
                    "onload=\"this.setAttribute('data-loaded','1')\" onerror=\"this.setAttribute('data-broken','1')\">"
                    f"<figcaption>{_e(caption)}</figcaption></figure>")
    if videos:
        body.append("<h2>Videos</h2>" + "".join(f'<p><a href="{_src(v)}">{_e(v)}</a></p>' for v in videos))
    if method:
        body.append(f"<h2>How it is measured</h2><p>{_e(method)}</p>")
    if details:
        body.append("<h2>Details</h2>")
    for t, header, rows in details:
        head, note = heading(t)
        body.append(f"<details><summary>{_e(head)}</summary>" + (f"<p>{_e(note)}</p>" if note else "") +
                    table(header, rows) + "</details>")
    body += [f"<p><small>{_e(f)}</small></p>" for f in facts]
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_e(title)}</title><style>{STYLE}</style>"
            "</head><body>" + "".join(body) + "</body></html>")
