"""What the commands hand the evaluation core of this benchmark: its policy names, its outcome scorer and its scene
measure. Each imports its heavy part (MuJoCo, the perception network) only when it applies, so a command run on a
lab's own robot, without the ``[sim]`` extra, can import this module and pass these along."""
from __future__ import annotations

import numpy as np

BENCHMARK_TAU = 0.02
"""The paper's termination threshold for this benchmark, in the raw units of its delta_ee actions (metres, radians):
the core assumes none (``rollout.resolve_tau``), this benchmark's configs set ``rollout.tau`` to it."""


def named_policy(name: str):
    """A zoo policy by its name, with the task it acts on: ``policies.resolve``'s ``named``."""
    from sc3_jax.benchmarks.bussing.zoo import ZOO, load_policy
    from sc3_jax.policies.resolve import SPELLINGS

    if name not in ZOO:
        raise ValueError(f"unknown policy {name!r}: expected {SPELLINGS}; zoo policies are {sorted(ZOO)}")
    return load_policy(name), ZOO[name].task


def perception_scorer(views, image_size, weights: str | None = None):
    """(PerceptionScorer, None), or (None, why not): the scorer reads left/right/wrist frames at 64x64 only.
    ``weights``: perception weights (None: the shipped ones). ``diagnose``'s ``scorer_for``."""
    if list(views) != ["left", "right", "wrist"] or tuple(image_size) != (64, 64):
        return None, f"the perception scorer reads left/right/wrist at 64x64; this model has {list(views)} at " \
                     f"{tuple(image_size)}"
    from sc3_jax.benchmarks.bussing import perception
    from sc3_jax.benchmarks.bussing.scorers import PerceptionScorer
    return PerceptionScorer(perception.load(weights or perception.DEFAULT_WEIGHTS)), None


def object_pixels(frames: np.ndarray) -> np.ndarray:
    """The benchmark's scene measure (``measures/permanence.py``): the fraction of pixels of its objects' colours
    (``tasks.OBJECTS``), frames uint8 [V, T, H, W, 3] -> [V, T]."""
    from sc3_jax.benchmarks.bussing.tasks import OBJECTS
    from sc3_jax.measures.permanence import pixels_of
    return pixels_of(frames, np.array([o.rgba[:3] for o in OBJECTS]))


def object_position(name: str):
    """The locator of one of its objects (``tasks.OBJECTS``, by name): the centroid of its colour's pixels
    (``locate.colour_mask``: ``permanence.pixels_of``' rule), frames [V, T, H, W, 3] -> (row, col) [V, T, 2] in pixels, nan in
    the wrist view and where too few show. Its arm has no colour of its own: the arm is left to the median rule."""
    def locate(frames: np.ndarray, views) -> np.ndarray:
        from sc3_jax.benchmarks.bussing.tasks import OBJECT_BY_NAME
        from sc3_jax.measures.locate import centroid, colour_mask, masked_views
        return masked_views(centroid(colour_mask(frames, np.array([OBJECT_BY_NAME[name].rgba[:3]]))), views)
    return locate


def locators():
    """Its ``benchmark.Locators``: each object by its colour; the arm by the median rule (no colour of its own)."""
    from sc3_jax.evaluation.benchmark import Locators
    from sc3_jax.benchmarks.bussing.tasks import OBJECT_NAMES
    return Locators(objects={n: object_position(n) for n in OBJECT_NAMES})
