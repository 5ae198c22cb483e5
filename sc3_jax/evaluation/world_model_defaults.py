"""How a world model is sampled when it is evaluated, in one place: ``Sampler``'s fields are options of both sweeps
(``sc3 sweep bench`` / ``sc3 sweep episodes``, which inherit them), and its steps (``SamplerSteps``: ``--sample-steps``,
``--inverse-steps``) those of ``sc3 sweep so101``, ``sc3 rollout``, ``sc3 diagnose`` and ``sc3 plan`` too, so a tau or a
U read in one command is read alike in the others. The defaults are the evaluation protocol's, not a saved model's
own ``sample.steps`` (None samples in those): why 2 forward steps and 1 inverse step, docs/sweep.md#sampler-steps;
the one set of option spellings, sc3_jax/commands/flags.py."""
from __future__ import annotations

import dataclasses
import math
import warnings


@dataclasses.dataclass(frozen=True, kw_only=True)
class SamplerSteps:
    """The evaluation sampler's Euler steps (None / 0: the world model's own setting): the one default of
    ``--sample-steps`` and ``--inverse-steps`` in every command that has them."""

    sample_steps: int | None = 2
    """forward-dynamics Euler steps per chunk (None: the world model's own sample.steps)"""
    inverse_steps: int | None = 1
    """Euler steps of the inverse-dynamics re-read that yields U_chunk (None: the world model's own
    sample.inverse_steps); it never changes the frames or the outcomes"""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Sampler(SamplerSteps):
    """The evaluation sampler (None / 0: the world model's own setting)."""
    episode_seconds: float | None = None
    """imagined horizon (None: the world model's rollout.episode_seconds)"""
    taus: tuple[float, ...] = (math.inf,)
    """candidate U_chunk thresholds; the calibration conditions choose one (inf: never stop)"""
    tau_units: str = "raw"
    """U_chunk's units, "raw" (the action's own) or "normalised" (per-dimension unit variance)"""
    batch: int = 6
    """initial conditions per world-model call (the resume unit)"""
    rollout_seed: int = 0
    """seed of the sampling noise: condition i's draws depend only on (rollout_seed, i)"""


def evaluation_config(cfg, settings: Sampler = Sampler()):
    """The world model's config ``cfg`` as it is evaluated under ``settings``: sample.steps, sample.inverse_steps and
    rollout.episode_seconds replaced where set, rollout.tau_units always (one unit convention for tau and U)."""
    from sc3_jax.core.config import replace

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
                      "/ rollout / diagnose --sample-steps 1)", stacklevel=2)
