"""The HTML page of a report (both sweeps: the simulator's and the simulator-free one).

A results store is something people hand each other: every value it puts into the page (policy names, warnings,
table cells, file names) is escaped here, attributes included, and a link or image names a file of the report's own
directory only (``safe_names.file_name``), so a store cannot put script or a foreign address into the page.
"""
from __future__ import annotations

import html
from urllib.parse import quote

STYLE = ("body{font-family:sans-serif;max-width:1100px;margin:1em auto;padding:0 1em}"
         "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:2px 6px}"
         "th{background:#eee}")


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _src(name: str) -> str:
    """A file of the report's directory as a relative address: never a scheme, an absolute path or '..'."""
    return quote(name.replace("/", "_").lstrip("."), safe="")


def page(title: str, paragraphs: list[str], warnings: list[str], tables: list[tuple[str, list[str], list[list[str]]]],
         images: list[str] = (), videos: list[str] = ()) -> str:
    """The page: ``title``, plain-text ``paragraphs``, bold ``warnings``, ``(title, header, rows)`` tables, images and
    video links (file names in the report's directory)."""
    body = [f"<h1>{_e(title)}</h1>"] + [f"<p>{_e(p)}</p>" for p in paragraphs]
    body += [f"<p><b>{_e(w)}</b></p>" for w in warnings]
    for heading, header, rows in tables:
        body.append(f"<h2>{_e(heading)}</h2><table><tr>" + "".join(f"<th>{_e(h)}</th>" for h in header) + "</tr>" +
                    "".join("<tr>" + "".join(f"<td>{_e(c)}</td>" for c in r) + "</tr>" for r in rows) + "</table>")
    body += [f'<h2>{_e(i.rsplit(".", 1)[0])}</h2><img src="{_src(i)}" alt="{_e(i)}" width=640>' for i in images]
    body += [f'<p><a href="{_src(v)}">{_e(v)}</a></p>' for v in videos]
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_e(title)}</title><style>{STYLE}</style>"
            "</head><body>" + "".join(body) + "</body></html>")
