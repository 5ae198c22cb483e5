"""SO-101's success read from where the block and the goal are in the frame, a scorer that fading cannot fool
(``--scorer sc3_jax.benchmarks.so101.scorer:block_at_goal``).

The learned detector (``sc3 train-detector``) learned "done = the block covers the goal", so an imagined rollout whose
goal disc fades reads as done. This rule reads the first view (the workspace camera): the goal disc's centre and
radius from the frame that shows most of it (the arm may hide it in some frames, a fading model in the late ones),
the block's pixels in every frame. Done
once, for ``CONSECUTIVE`` frames in a row, the block shows at least ``MIN_BLOCK`` of its first frame's pixels (a
faded block is not a placed one), its centre lies within the disc, and it has not moved between them (the simulator
wants it at rest with the jaw open). A block that never left its place is not done (the simulator wants it lifted):
it must have been ``MIN_TRAVEL`` disc radii away from its start first. numpy only.
"""
from __future__ import annotations

import numpy as np

from sc3_jax.benchmarks.so101.hooks import block_mask, goal_mask

CRITERION = "success"
CONSECUTIVE = 2
MIN_BLOCK = 0.3  # of the first frame's block pixels: the jaws hide half of it as they let go
MIN_TRAVEL = 1.0  # in goal-disc radii: the block's centre left its first place by this much at some point
MAX_STILL = 0.4  # in goal-disc radii: the block's centre moved less than this between the counted frames


def _centres(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pixel count [T], centre (row, col) [T, 2], nan where none)."""
    n = mask.sum((1, 2)).astype(np.float64)
    rows, cols = np.indices(mask.shape[1:])
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.stack([(mask * rows).sum((1, 2)) / n, (mask * cols).sum((1, 2)) / n], -1)
    return n, c


def done_frames(frames: np.ndarray) -> np.ndarray:
    """bool [T]: frame t (with t-1 before it) shows the block at rest on the goal disc; frames uint8 [T, H, W, 3]
    of the workspace view, frame 0 a real one (the block's first place and amount)."""
    goals = goal_mask(frames)
    goal = goals[goals.sum((1, 2)).argmax()]
    area = goal.sum()
    if area == 0:  # no goal to place on: nothing can be done
        return np.zeros(len(frames), bool)
    gc = np.argwhere(goal).mean(0)
    radius = np.sqrt(area / np.pi)
    n, c = _centres(block_mask(frames))
    if n[0] == 0:
        return np.zeros(len(frames), bool)
    visible = n >= MIN_BLOCK * n[0]
    on_goal = visible & (np.linalg.norm(c - gc, axis=1) < radius)
    travelled = np.maximum.accumulate(np.nan_to_num(np.linalg.norm(c - c[0], axis=1)) * visible) >= MIN_TRAVEL * radius
    still = np.r_[False, np.linalg.norm(np.diff(c, axis=0), axis=1) < MAX_STILL * radius]
    return on_goal & still & travelled


def block_at_goal(view) -> dict[str, bool]:
    """The scorer: ``{"success": done}`` for a ``RolloutView`` (its first view read)."""
    d = done_frames(np.asarray(view.frames[0]))
    run = 0
    for v in d:
        run = run + 1 if v else 0
        if run >= CONSECUTIVE:
            return {CRITERION: True}
    return {CRITERION: False}
