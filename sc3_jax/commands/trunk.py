"""``sc3 trunk save --run RUN --out DIR`` / ``sc3 trunk branch --trunk TRUNK --steps N --out DIR``: a long WSD run
(the trunk) as state that travels between machines, and the annealed branches of it that are measured and shipped
(docs/world_model.md, "The trunk")."""
from __future__ import annotations

import dataclasses

from sc3_jax.commands import run_group

SUMMARY = "a WSD trunk: save its travelling state, or anneal a branch of it and export it"  # `sc3 --help`'s line
RESUME = "rerun the same command: a branch resumes from its last checkpoint"


@dataclasses.dataclass(frozen=True)
class Save:
    """Save a run's latest checkpoint as state that travels: a world model plus its optimizer moments, step, rng,
    data position and lineage, to commit and resume elsewhere (--train.resume-from DIR)."""

    run: str
    """the `sc3 train` workdir of the trunk"""
    out: str
    """where to write it (replaced whole, in one step)"""
    moments: str = "bfloat16"
    """the optimizer moments' storage dtype: bfloat16 (half the bytes) or float32 (the resume exact to the bit)"""


@dataclasses.dataclass(frozen=True)
class Branch:
    """Anneal a copy of a WSD trunk's latest state to a learning rate of ~0 over --steps steps and export it (the
    model to measure and ship); the trunk itself is not touched."""

    trunk: str
    """the trunk: its `sc3 train` workdir, or its travelling state (`sc3 trunk save`)"""
    steps: int
    """the decay's length in steps (at most the steps the trunk has trained; 10-20% of them is usual)"""
    out: str
    """the exported branch (a world model with its lineage.json)"""
    workdir: str | None = None
    """the branch's own run directory (None: beside the trunk, TRUNK_branch_sSTEP_dSTEPS)"""
    data: str | None = None
    """the trunk's episode store, where it is not at the path the trunk recorded"""
    progress: bool = True
    """a progress bar on stderr (--no-progress: none)"""


SUBCOMMANDS: dict[str, type] = {"save": Save, "branch": Branch}


def _save(a: Save) -> int:
    from sc3_jax.train import branch, lineage, trunk_state

    out = branch.save_run(a.run, a.out, a.moments)
    meta, lin = trunk_state.read_meta(out), lineage.read(out)
    print(f"saved {a.run} at step {meta['step']} ({lin['windows']:,} windows since initialisation) -> {out}")
    return 0


def _branch(a: Branch) -> int:
    from sc3_jax.train import branch

    out, lin = branch.branch(a.trunk, a.steps, a.out, a.workdir, a.data, a.progress)
    b = lin.get("branch", {})
    print(f"branch: decayed from step {b.get('decay_start')} to {b.get('to_step')} "
          f"({lin['windows']:,} windows since initialisation) -> {out}")
    return 0


_RUN = {"save": _save, "branch": _branch}


def main(argv: list[str]) -> int:
    return run_group("trunk", "A WSD trunk's travelling state and its annealed branches.", SUBCOMMANDS, _RUN, argv)
