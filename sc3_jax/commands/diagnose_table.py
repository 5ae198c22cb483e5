"""``sc3 diagnose-table --world-model DIR ... [--baseline NAME]``: several models' ``sc3 diagnose`` results side by side
(sc3_jax/evaluation/diagnose_table.py)."""
from __future__ import annotations

import dataclasses
from typing import Annotated

from sc3_jax.commands import one_or_more, parse
from sc3_jax.core.errors import UserError

SUMMARY = "several models' diagnostics side by side"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args:
    """Several world models' `sc3 diagnose` results side by side: the offline half of an ablation table (the full
    recipe and its ablations trained at one budget)."""

    world_model: Annotated[tuple[str, ...], one_or_more("DIR")]
    """world-model dirs, each holding diagnose.json and config.json"""
    baseline: str | None = None
    """label of the row every other row is compared with"""
    out: str | None = None
    """also write the table (markdown) here"""


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "diagnose-table")
    if not a.world_model:  # tyro takes a positional tuple as zero or more; argparse asked for one at least
        raise UserError("give at least one world-model directory")
    from sc3_jax.core import atomic
    from sc3_jax.evaluation import diagnose_table

    rows = {}
    for m in a.world_model:
        label, row = diagnose_table.load(m)
        if label in rows:
            raise UserError(f"two models are labelled {label!r}; give each its own directory name")
        rows[label] = row
    text = diagnose_table.table(rows, a.baseline)
    print(text)
    if a.out:
        atomic.write_text(a.out, text + "\n")
    return 0
