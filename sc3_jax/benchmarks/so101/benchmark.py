"""The SO-101 pick-and-place benchmark as the commands look it up (``sc3_jax.evaluation.benchmark.get("so101")``): its
sweep (``sweep.py``: the simulator's outcomes beside the imagined ones, scored by a detector or a scorer), its scene
measures (the block and the goal marker; the arm: ``hooks.py``) and its zoo's policy names. No outcome scorer of
imagined frames for ``sc3 diagnose`` / ``sc3 rollout`` (its sweep names one: ``--detector`` or ``--scorer``).
Importing this loads no simulator."""
from __future__ import annotations

from pathlib import Path

from sc3_jax.evaluation.benchmark import Benchmark

from .hooks import arm_pixels, locators, named_policy, object_pixels
from .sweep import So101SweepConfig


def run_sweep(cfg: So101SweepConfig) -> Path:
    """``sweep.run``, looked up when called."""
    from . import sweep
    return sweep.run(cfg)


def describe_sweep(cfg: So101SweepConfig, out: Path) -> list[str]:
    """What ran and how far the scorer agrees with the simulator on the real episodes (``scorer_check.json``)."""
    from sc3_jax.core.atomic import read_json

    from .sweep import CHECK_FILE
    what = f"the detector {cfg.detector}" if cfg.detector else f"the scorer {cfg.scorer}"
    lines = [f"SO-101: {cfg.episodes} simulator seeds per policy, real in the simulator, imagined inside "
             f"{cfg.world_model}, scored by {what}"]
    if not (out / CHECK_FILE).is_file():  # every policy's real outcomes came from lerobot-eval: no real frames here
        return lines + [f"{what} was not checked against the simulator: no real episode ran here (--lerobot-eval)"]
    c = read_json(out / CHECK_FILE)
    return lines + [f"{what} on the real episodes agrees with the simulator on {c['agreement']:.2f} of {c['all']['n']}"]


BENCHMARK = Benchmark(name="so101", sweep_config=So101SweepConfig, run_sweep=run_sweep, describe_sweep=describe_sweep,
                      measures={"objects": object_pixels, "arm": arm_pixels}, named_policy=named_policy,
                      locators=locators())
