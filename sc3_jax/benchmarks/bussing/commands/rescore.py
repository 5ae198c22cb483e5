"""``sc3 rescore RESULTS [--perception WEIGHTS]``: re-score a store's stored frames with other scorer weights
(sc3_jax/benchmarks/bussing/rescore.py says what is re-scored and why ``--state-reader``)."""
from __future__ import annotations

import dataclasses
import json

import tyro

from sc3_jax.commands import parse

# the bussing benchmark's own command (its perception scorer), as `sc3 sim` is: --help says so
SUMMARY = "re-score a bussing sweep's stored frames with other perception weights"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args:
    """Re-score a sweep's results store with other perception weights, without re-running a single rollout."""

    results: tyro.conf.Positional[str]
    """a sweep's --out directory"""
    perception: str | None = None
    """perception weights (None: the shipped ones)"""
    state_reader: str | None = None
    """the weights that read the gripper state inside the store's imagined rollouts (needed when they were the
    scorer's and the scorer changes)"""
    progress: bool = True
    """a progress bar on stderr (--no-progress: none, for batch logs)"""


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "rescore")
    from sc3_jax.benchmarks.bussing import rescore

    changed = rescore.rescore(a.results, a.perception, a.state_reader, progress=a.progress)
    print(json.dumps({"results": a.results, "rollouts_changed": changed}))
    print(f"rerun the report: sc3 report {a.results}")
    return 0
