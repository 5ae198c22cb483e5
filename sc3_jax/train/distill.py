"""The sampler's distillation teacher (``flow.distill_teacher``; the loss is ``flow.distill_loss``): its config
checked against the student's, its params read with the student's shardings (never checkpointed: a resumed run reads
them again), its normalisation checked, and the jitted train step with the teacher bound (``WithTeacher``)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np

from sc3_jax.model import checkpoint
from sc3_jax.core.config import Config
from sc3_jax.core.errors import UserError
from sc3_jax.model.shapes import check_shapes

# fields that set how a model runs, not what it computes: a distillation teacher may differ from its student there
RUN_FIELDS = ("dtype", "param_dtype", "remat", "scan_layers", "attention_impl", "attention_block", "tokenizer_path")


def teacher_config(cfg: Config, check_model: bool = True) -> Config | None:
    """The config of ``cfg.flow.distill_teacher`` (None when distillation is off), checked: its model config must
    be the student's (up to ``RUN_FIELDS``; ``check_model=False``: not checked, for a FLOP count that lowers the
    student at another depth, ``sizing.step_flops``), and so must its flow.from_present (the source both sample
    from); the student must start from saved params and must not self-force.
    The teacher runs with the student's model config but its own compute dtype and its own time grid -- as it is
    sampled when evaluated."""
    f = cfg.flow
    if not f.distill_teacher:
        return None
    if f.distill_steps < 1:
        raise UserError(f"flow.distill_steps = {f.distill_steps}: the teacher's Euler steps, >= 1 (the student "
                        "takes 1)")
    if not cfg.train.init_from:
        raise UserError("flow.distill_teacher needs a student to start from: add --train.init-from DIR (usually the "
                        "teacher itself)")
    if f.self_forcing:
        raise UserError(f"flow.distill_teacher replaces the flow loss, flow.self_forcing = {f.self_forcing} is part of "
                        "it: set --flow.self-forcing 0")
    try:
        teacher = checkpoint.read_config(f.distill_teacher, what="flow.distill_teacher ")
    except FileNotFoundError as e:
        raise UserError(str(e)) from None
    have, want = dataclasses.asdict(teacher.model), dataclasses.asdict(cfg.model)
    for k in want if check_model else ():
        if k not in RUN_FIELDS and json.dumps(have.get(k)) != json.dumps(want[k]):
            raise UserError(f"flow.distill_teacher {f.distill_teacher}: its model.{k} is {have.get(k)!r}, this run's "
                            f"{want[k]!r}: distil into the teacher's own model config (train with its config, or set "
                            f"--model.{k.replace('_', '-')})")
    if teacher.flow.from_present != f.from_present:  # teacher and student sample from one source (distill_loss)
        raise UserError(f"flow.distill_teacher {f.distill_teacher}: its flow.from_present is "
                        f"{teacher.flow.from_present}, this run's {f.from_present}: set --flow.from-present "
                        f"{teacher.flow.from_present}")
    return dataclasses.replace(teacher, model=dataclasses.replace(cfg.model, dtype=teacher.model.dtype))


def load_teacher(cfg: Config, shardings=None) -> dict:
    """The distillation teacher's params (``cfg.flow.distill_teacher``, checked by ``teacher_config``), as the
    student's param dtype and placed with ``shardings`` (the student's params'); never part of the train state,
    so never checkpointed: a resumed run reads them again from the same path."""
    teacher_config(cfg)
    src = Path(cfg.flow.distill_teacher)
    have = {jax.tree_util.keystr(k): v.shape for k, v in
            jax.tree_util.tree_flatten_with_path(checkpoint.param_shapes(cfg))[0]}
    check_shapes(have, checkpoint.source_shapes(src), f"flow.distill_teacher {src}: params do not fit this model "
                                                      "config:")
    return checkpoint.load_params(src, cfg, shardings=shardings)


def check_teacher_stats(cfg: Config, stats) -> None:
    """The teacher must read actions and poses in the student's units (its norm stats, where it has any)."""
    if not cfg.flow.distill_teacher:
        return
    path = Path(cfg.flow.distill_teacher) / "norm_stats.json"
    if not path.exists():
        return
    theirs = checkpoint.read_norm_stats(path.parent)
    same = theirs.action_space == stats.action_space and all(
        np.array_equal(getattr(theirs, k), getattr(stats, k)) for k in ("mean", "std", "pose_mean", "pose_std"))
    if not same:
        raise UserError(f"{path}: the teacher's action normalisation differs from this run's "
                        f"({Path(cfg.train.workdir) / 'norm_stats.json'}): start the student from the teacher "
                        "(--train.init-from TEACHER) in a new --train.workdir")


class WithTeacher:
    """A jitted train step with the distillation teacher's params bound as its last argument: called, lowered and
    traced as step(state, batch), like the step without one."""

    def __init__(self, fn, teacher):
        self.fn, self.teacher = fn, teacher

    def __call__(self, state, batch):
        return self.fn(state, batch, self.teacher)

    def lower(self, state, batch):
        return self.fn.lower(state, batch, self.teacher)

    def trace(self, state, batch):
        return self.fn.trace(state, batch, self.teacher)
