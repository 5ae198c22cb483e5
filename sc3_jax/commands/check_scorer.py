"""``sc3 check-scorer --data STORE --scorer SPEC``: a scorer's agreement with the real outcomes of a store's labelled
episodes, on their real frames (``sc3_jax/evaluation/scorer_check.py``) -- the check before a sweep trusts it."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from sc3_jax.core import atomic
from sc3_jax.commands import parse
from sc3_jax.core.errors import UserError

SUMMARY = "a scorer's agreement with the labels of real episodes, on their frames"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args:
    """Run a scorer on every labelled real episode of a store (its recorded frames and state, as a sweep hands it
    an imagined rollout) and say how often it agrees with the label, with a Wilson 95% interval."""

    data: str
    """an episode store whose episodes carry labels (meta.json "labels": {criterion: bool}; `sc3 data
    import-lerobot` keeps next.success as labels.success)"""
    scorer: str
    """the scorer, as `sc3 sweep --scorer` takes it: package.module:attr or detector:DIR"""
    criterion: str = "success"
    """the label and the scorer's criterion compared"""
    out: str | None = None
    """also write the result as JSON here (the episodes it disagrees on included)"""
    progress: bool = True
    """a progress bar on stderr (--no-progress: none, for batch logs)"""


def main(argv: list[str]) -> int:
    from sc3_jax.evaluation import scorer_check

    a = parse(Args, argv, "check-scorer")
    if a.out is not None:  # said before the episodes are scored, not after
        out = Path(a.out).absolute()
        if out.is_dir() or next(p for p in out.parents if p.exists()).is_file():
            raise UserError(f"--out {a.out}: not a file that can be written (a folder, or under a file)")
    r = scorer_check.check(a.data, a.scorer, a.criterion, a.progress)
    iv = r["interval"]
    print(f"{a.scorer} agrees with the labels on {r['agreement']:.3f} [{iv['lo']:.3f}, {iv['hi']:.3f}] of {r['n']} "
          f"episodes: done {r['scorer_done']} times where the labels say {r['labels_done']} ({r['false_done']} false "
          f"done, {r['missed']} missed)")
    if r["disagree"]:
        print("disagrees on: " + " ".join(r["disagree"][:20]) + (" ..." if len(r["disagree"]) > 20 else ""))
    if a.out is not None:
        atomic.write_json(a.out, r)
    return 0
