"""``sc3 report RESULTS ... [--out DIR]``: tables, plots and videos from a sweep's results store."""
from __future__ import annotations

import dataclasses
from typing import Annotated

import tyro

from sc3_jax.commands import one_or_more, parse
from sc3_jax.errors import UserError


@dataclasses.dataclass(frozen=True)
class Args:
    """Report of a sweep's results store."""

    results: Annotated[tyro.conf.Positional[tuple[str, ...]], one_or_more("RESULTS")]
    """the sweep's --out directory (a sharded sweep's: all its shards), or several shares of one sweep, read as one"""
    out: str | None = None
    """report directory (default: the first RESULTS/report)"""
    videos: int = 3
    """side-by-side example videos"""
    taus: tuple[float, ...] | None = None
    """termination thresholds (default: the sweep's candidates); evaluated from the stored U_chunk, no new
    rollouts. U_chunk is in the sweep's units (rollout.tau_units)"""
    draws: int = 2000
    """paired bootstrap draws for the 95% intervals"""


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "report")
    if not a.results:  # tyro takes a positional tuple as zero or more; argparse asked for one at least
        raise UserError("give at least one RESULTS store")
    from sc3_jax.evaluate import report  # after parsing: --help and a typo need not load the plotting stack

    md = report.render(list(a.results), a.out or f"{a.results[0]}/report", a.videos, a.taus, a.draws)
    print(f"report: {md}")
    return 0
