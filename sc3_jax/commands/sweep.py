"""``sc3 sweep [--OPTION VALUE ...]``: policies x initial conditions, real and inside the world model, then the
report."""
from __future__ import annotations

import json
from pathlib import Path

from sc3_jax.commands import parse
from sc3_jax.evaluate.sweep import SweepConfig as Args  # the protocol is the command's options


def main(argv: list[str]) -> int:
    cfg = parse(Args, argv, "sweep")
    from sc3_jax.evaluate import report, sweep

    out = sweep.run_sweep(cfg)
    if out != Path(cfg.out):  # one shard of several: the report reads them all once every shard has finished
        print(f"shard done: {out}; once every shard has finished: sc3 report {cfg.out}")
        return 0
    md = report.render(out, out / "report")
    t = json.loads((out / "report" / "report.json").read_text())
    title, header, rows = next(x for x in report.tables(t) if x[0].startswith("Faithfulness, end to end"))
    print(f"## {title}\n\n| " + " | ".join(header) + " |\n" + "".join("| " + " | ".join(r) + " |\n" for r in rows))
    print("\n".join(report.verdict(t) + t.get("warnings", [])))
    print(f"report: {md} (and report.html, report.json, correlation.png)")
    return 0
