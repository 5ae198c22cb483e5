"""``sc3 curve SPEC.json --out DIR``: faithfulness against training compute over several sweeps."""
from __future__ import annotations

import dataclasses

import tyro

from sc3_jax.commands import parse

SUMMARY = "faithfulness against training compute over several sweeps"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args:
    """Faithfulness against training compute: one table and one plot over several checkpoints' sweeps
    (sc3_jax/evaluation/curve.py)."""

    spec: tyro.conf.Positional[str]
    """JSON: {"title": ..., "points": [{"label", "store", "steps", "batch", "device", "hours"}, ...]}"""
    out: str
    """directory for curve.md, curve.png, curve.json"""
    draws: int = 2000
    """paired bootstrap draws for the 95% intervals"""


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "curve")
    from sc3_jax.evaluation import curve

    print(f"curve: {curve.render(a.spec, a.out, a.draws)}")
    return 0
