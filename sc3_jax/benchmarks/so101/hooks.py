"""What the commands hand the evaluation core of the SO-101 benchmark: its scene measure (the block and the goal
marker, the scene's only objects). numpy only: importing it needs no simulator."""
from __future__ import annotations

import numpy as np

from sc3_jax.benchmarks.so101.env import BLOCK_RGBA, GOAL_RGBA
from sc3_jax.evaluate.permanence import pixels_of


def object_pixels(frames: np.ndarray) -> np.ndarray:
    """The benchmark's scene measure (``evaluate/permanence.py``): the fraction of pixels of the block's and the goal
    marker's colours, frames uint8 [V, T, H, W, 3] -> [V, T]. The marker renders paler than its rgba (chromaticity
    0.18 / 0.56 / 0.26 against 0.13 / 0.65 / 0.22, at 96+ brightness): a wider tolerance and a lower floor for it (the
    background and the arm lie ~0.4 away)."""
    return (pixels_of(frames, BLOCK_RGBA[None, :3], min_brightness=120.0)
            + pixels_of(frames, GOAL_RGBA[None, :3], tol=0.2, min_brightness=60.0))
