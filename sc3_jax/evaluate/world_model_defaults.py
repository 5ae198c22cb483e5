"""One set of evaluation settings for a world model, whichever command evaluates it: ``sc3 sweep`` computes U_chunk and
the imagined frames with ``SweepConfig``'s sampler settings (2 forward Euler steps, 1 inverse re-read step, 12 s
horizon, raw U units) rather than the checkpoint's own (e.g. 8 and 8), and ``sc3 rollout`` / ``sc3 diagnose`` apply
the same ones through :func:`evaluation_config`, so a tau or a U read in one is read alike in the others. The values
live in one place, ``SweepConfig``'s field defaults (where their measurements are cited); this module only applies
them, and imports no sweep code, so that the sweep can call it too."""
from __future__ import annotations

import warnings
from typing import Protocol


class EvaluationSettings(Protocol):
    """The fields of ``evaluate.sweep.SweepConfig`` that set how a world model is sampled (None / 0: the model's
    own)."""
    sample_steps: int | None
    inverse_steps: int | None
    episode_seconds: float | None
    tau_units: str


def evaluation_config(cfg, settings: EvaluationSettings):
    """The world model's config ``cfg`` as it is evaluated under ``settings`` (a ``SweepConfig``; the commands pass
    ``SweepConfig()``, the defaults): sample.steps, sample.inverse_steps and rollout.episode_seconds replaced where
    set, rollout.tau_units always (one unit convention for tau and U)."""
    from sc3_jax.config import replace

    cfg = replace(cfg, sample={k: v for k, v in (("steps", settings.sample_steps),
                                                 ("inverse_steps", settings.inverse_steps)) if v})
    if settings.episode_seconds:
        cfg = replace(cfg, rollout=dict(episode_seconds=settings.episode_seconds))
    return replace(cfg, rollout=dict(tau_units=settings.tau_units))


def warn_if_student_off_its_step(cfg) -> None:
    """A distilled student (``flow.distill_teacher``) was trained to sample in 1 forward step; at the sweep's default
    2 it is neither itself nor its teacher. Called with the config a command will sample, after its overrides."""
    if cfg.flow.distill_teacher and cfg.sample.steps != 1:
        warnings.warn(f"this world model is a 1-step student of {cfg.flow.distill_teacher} (flow.distill_teacher), "
                      f"sampled here in {cfg.sample.steps} forward steps; it was trained for 1 (sc3 sweep "
                      "--sample-steps 1, sc3 rollout / diagnose --sample.steps 1)", stacklevel=2)
