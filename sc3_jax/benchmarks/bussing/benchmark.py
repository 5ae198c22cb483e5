"""The simulated table-bussing benchmark as the commands look it up (``sc3_jax.evaluation.benchmark.get("bussing")``,
alias "bench"): its sweep (``sweep.py``: real rollouts in its simulator, offline and online ones inside the world model,
scored by its perception network), its scene measure (its objects' pixels: its arm is grey like its floor, so no
colour tells the arm apart) and outcome scorer, its zoo's policy names (``hooks.py``), its tasks' prompts
(``tasks.py``) and its outcome categories' words. Importing this loads neither MuJoCo nor the perception network."""
from __future__ import annotations

from sc3_jax.evaluation.benchmark import Benchmark

from .hooks import locators, named_policy, object_pixels, perception_scorer
from .sweep import SweepConfig
from .tasks import PROMPTS

# its other names, read by the registry (evaluation/benchmark.py) from this source without importing it: `sc3 sweep
# bench` (README command 1, the golden records) is this benchmark's sweep
ALIASES = ("bench",)
# its outcome categories (the first criterion an object fails, metrics.outcome_category) in the simulator's words
# (mixture.py's), as `sc3 diagnose --benchmark bussing` prints them
CATEGORY_NAMES = {"no_failure": "placed", "placing": "dropped / off target", "lifting": "missed (never lifted)",
                  "language": "wrong container"}


def run_sweep(cfg: SweepConfig):
    """``sweep.run_sweep``, looked up when called (a test may stand in for it)."""
    from . import sweep
    return sweep.run_sweep(cfg)


BENCHMARK = Benchmark(name="bussing", sweep_config=SweepConfig, run_sweep=run_sweep,
                      measures={"objects": object_pixels}, outcome_scorer=perception_scorer,
                      named_policy=named_policy, locators=locators(), prompts=PROMPTS,
                      category_names=CATEGORY_NAMES)
