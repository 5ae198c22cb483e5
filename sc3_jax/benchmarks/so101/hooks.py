"""What the commands hand the evaluation core of the SO-101 benchmark: its scene measures (the block and the goal
marker, the scene's only objects; the arm), the pixel masks they and the scorer share, and its zoo's policy names.
numpy only: importing it needs no simulator (the zoo is imported when a name is looked up).

The masks go by which channel dominates a pixel's chromaticity (r, g, b over their sum), not by a distance to the
material's colour: the goal disc renders pale and at a different chromaticity in each camera (lit from the side it
washes toward white: (0.24, 0.42, 0.34) in the workspace view against its material's (0.13, 0.65, 0.22)), while the
scene has one green thing (the disc), one purple one (the block: red and blue over green) and one yellow one (the
arm: red and green over blue); the floor is blue and the servos are dark."""
from __future__ import annotations

import numpy as np

MIN_BRIGHTNESS = 60.0  # r + g + b: below it, dark pixels' chromaticity is noise
MARGIN = 0.1  # how far the dominant channels' share must exceed the others'


def _chroma(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(frames, np.float32)
    s = x.sum(-1)
    return x / np.maximum(s, 1.0)[..., None], s >= MIN_BRIGHTNESS


def goal_mask(frames: np.ndarray) -> np.ndarray:
    """bool [..., H, W]: the goal disc's pixels (green over red and blue)."""
    c, lit = _chroma(frames)
    return lit & (c[..., 1] > c[..., 0] + MARGIN) & (c[..., 1] > c[..., 2] + MARGIN / 2)


def block_mask(frames: np.ndarray) -> np.ndarray:
    """bool [..., H, W]: the block's pixels (red and blue over green)."""
    c, lit = _chroma(frames)
    return lit & (c[..., 0] > c[..., 1] + MARGIN) & (c[..., 2] > c[..., 1] + MARGIN)


def arm_mask(frames: np.ndarray) -> np.ndarray:
    """bool [..., H, W]: the arm's yellow parts (red and green over blue; the black servos are not counted)."""
    c, lit = _chroma(frames)
    return lit & (c[..., 0] > c[..., 2] + 2 * MARGIN) & (c[..., 1] > c[..., 2] + 2 * MARGIN)


def object_pixels(frames: np.ndarray) -> np.ndarray:
    """The benchmark's scene measure (``measures/permanence.py``): the fraction of the block's and the goal marker's
    pixels, frames uint8 [V, T, H, W, 3] -> [V, T]."""
    return (block_mask(frames) | goal_mask(frames)).mean((-2, -1))


def arm_pixels(frames: np.ndarray) -> np.ndarray:
    """The arm's scene measure: the fraction of its yellow parts' pixels, frames [V, T, H, W, 3] -> [V, T]."""
    return arm_mask(frames).mean((-2, -1))


def arm_position(frames: np.ndarray, views) -> np.ndarray:
    """The arm's image position (``benchmark.Locators.arm``): the centroid of its yellow parts, frames [V, T, H, W, 3]
    -> (row, col) [V, T, 2] in pixels; nan in the wrist view (it moves with the arm) and where too few show."""
    from sc3_jax.measures.locate import centroid, masked_views
    return masked_views(centroid(arm_mask(frames)), views)


def block_position(frames: np.ndarray, views) -> np.ndarray:
    """The block's image position: the centroid of its purple pixels (red and blue over green), in pixels, in the
    views that stay put (the workspace camera; nan in the wrist view, where the block is a blur that moves with the
    camera) -> [V, T, 2]."""
    from sc3_jax.measures.locate import centroid, masked_views
    return masked_views(centroid(block_mask(frames)), views)


# what SO-101's velocity actions move in its 14-D state (env.STATE_NAMES), for a model whose action space does not
# declare it (ActionSpace.measured): the gripper frame's xyz; the gripper target is compared with nothing
MOVES = {"dx": "ee_x", "dy": "ee_y", "dz": "ee_z"}


def locators():
    """Its ``benchmark.Locators``: the arm, the block (pixels of the workspace view), what the actions move."""
    from sc3_jax.evaluation.benchmark import Locators
    return Locators(arm=arm_position, objects={"block": block_position}, moves=MOVES)


def named_policy(name: str):
    """An SO-101 zoo policy by its name (``zoo.named_policy``, imported when called: the zoo loads JAX)."""
    from sc3_jax.benchmarks.so101.zoo import named_policy as zoo_named
    return zoo_named(name)
