"""A WSD trunk's travelling state saved from its workdir (``sc3 trunk save``) and its branches (``sc3 trunk branch``):
a copy of the trunk's state annealed to a learning rate of ~0 over N
steps and exported -- the model that is measured and shipped -- while the trunk itself trains on at its peak rate.
The branch resumes the trunk's exact state (``trunk_state``), so it draws the windows the trunk would have drawn
next, and its lineage records where it left the trunk."""
from __future__ import annotations

import contextlib
import dataclasses
import os
from pathlib import Path

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.train import lineage, trunk_state


def save_run(workdir: str | Path, out: str | Path, moments: str = "bfloat16") -> Path:
    """The travelling state of the ``sc3 train`` run at ``workdir`` (its latest checkpoint), written to ``out``."""
    from sc3_jax.core.config import config_from_dict
    from sc3_jax.data.norm_stats import NormStats
    from sc3_jax.model import checkpoint, sharding
    from sc3_jax.train import train

    workdir = Path(workdir)
    if not (workdir / "config.json").is_file():
        raise UserError(f"{workdir}: not a `sc3 train` run (no config.json)")
    cfg = config_from_dict(atomic.read_json(workdir / "config.json", "restore it from a copy"))
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, workdir=str(workdir)))
    try:  # a run whose config.json predates its robot facts: recorded from its store while that is here
        cfg = checkpoint.with_robot(cfg, checkpoint._recorded_robot(workdir, cfg))
    except UserError:
        pass
    mngr = train.checkpoint_manager(cfg, read_only=True)  # the trunk may be training: touch nothing of its
    if mngr.latest_step() is None:
        raise UserError(f"{workdir}: no checkpoint yet (the run saves one every train.ckpt_every steps)")
    state, data_state = train.restore(mngr, cfg, sharding.make_mesh(cfg.mesh))
    mngr.close()
    lin = lineage.read(workdir) or lineage.begin(None, cfg, workdir.name, 0)
    return trunk_state.write(out, cfg, NormStats.load(workdir / "norm_stats.json"), state, data_state, lin, moments,
                             head=workdir / "state_head.npz")


def default_workdir(source: Path, step: int, steps: int) -> Path:
    return source.parent / f"{source.name}_branch_s{step}_d{steps}"


def start_state(source: Path, workdir: Path) -> Path:
    """The travelling state the branch starts from: ``source`` itself, or (a trunk's workdir) its latest checkpoint
    saved into the branch's workdir (float32 moments: the branch continues the trunk exactly)."""
    if trunk_state.is_state(source):
        return source
    if not (source / "config.json").is_file():
        raise UserError(f"{source}: neither a trunk's `sc3 train` workdir nor a travelling state (scripts/trunk.sh "
                        "save)")
    return save_run(source, workdir / "start", moments="float32")


def branch(source: str | Path, steps: int, out: str | Path, workdir: str | Path | None = None,
           data: str | None = None, progress: bool = True) -> tuple[Path, dict]:
    """Anneal a copy of the trunk at ``source`` over ``steps`` steps and export it to ``out``; (out, its lineage)."""
    from sc3_jax.model import checkpoint
    from sc3_jax.train import train

    source = Path(source)
    if not source.exists():
        raise UserError(f"{source}: no such trunk (a `sc3 train` workdir or a travelling state)")
    if steps < 1:
        raise UserError(f"--steps {steps}: a branch anneals over at least 1 step")
    step = trunk_state.read_meta(source)["step"] if trunk_state.is_state(source) else _latest_step(source)
    check_branch(step, steps)
    t = checkpoint.read_config(source).train
    if t.schedule != "wsd" or t.decay_start is not None:  # before anything is read or written
        raise UserError(f"{source}: not a WSD trunk (train.schedule {t.schedule!r}, decay_start {t.decay_start}); "
                        "a branch anneals a run that holds its peak rate (--train.schedule wsd)")
    work = Path(workdir) if workdir else default_workdir(source, step, steps)
    work.mkdir(parents=True, exist_ok=True)
    start = start_state(source, work)
    cfg = checkpoint.read_config(start)
    t = cfg.train
    cfg = dataclasses.replace(
        cfg, data=dataclasses.replace(cfg.data, path=data or cfg.data.path),
        train=dataclasses.replace(t, workdir=str(work), steps=step + steps, decay_start=step,
                                  resume_from=str(start.absolute()), init_from=None, progress=progress))
    if not (Path(cfg.data.path) / "dataset.json").is_file():
        raise UserError(f"the trunk's data {cfg.data.path} is not here: give --data STORE (the same episodes)")
    _share_latents(source, work)
    train.train(cfg)
    out = checkpoint.export(work, out, dtype=np.float32)
    return out, lineage.read(out)


def check_branch(step: int, steps: int) -> None:
    """A decay longer than the training it anneals is another run, not a branch (Haegele et al.: 10-20% of it)."""
    if steps > step:
        raise UserError(f"--steps {steps}: a branch's decay must not be longer than the {step} steps its trunk has "
                        f"trained (its budget; 10-20% of them is usual): use --steps {max(1, step // 5)}, or let the "
                        "trunk train longer")


def _latest_step(workdir: Path) -> int:
    steps = [int(p.name) for p in (workdir / "checkpoints").glob("*") if p.name.isdigit()]
    if not steps:
        raise UserError(f"{workdir}: no checkpoint yet (the run saves one every train.ckpt_every steps)")
    return max(steps)


def _share_latents(source: Path, work: Path) -> None:
    """The trunk's cached latents (same store, tokenizer and views: the cache's manifest checks it) instead of
    encoding every episode again."""
    mine, theirs = work / "latents", source / "latents"
    if theirs.is_dir() and not os.path.lexists(mine):
        with contextlib.suppress(OSError):  # no links here: the branch encodes its own cache (minutes)
            mine.symlink_to(theirs.absolute(), target_is_directory=True)
