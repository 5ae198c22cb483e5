"""SO-101's success as the simulator reads it, from where the zoo's estimator puts the block and the goal
(``--scorer sc3_jax.benchmarks.so101.placed:block_placed``).

The simulator's rule (``env.py``): the block was lifted, rests within the success radius of the goal, the jaw open.
This scorer asks the same of every frame, with the block's xyz and the goal's xy estimated from the workspace view
and the robot state by the zoo's full estimator (``zoo.estimate``: 0.53 cm held-out block error), the jaw read from
the state's gripper command. One frame suffices, because a real episode ends on the frame it succeeds (its jaw is
open in that frame only). The pixel rule (``scorer.block_at_goal``) asks for the block's colour on the goal disc,
which the closing jaws hide in most real successes: it agreed with the simulator on 0.72 of the 224 collected
episodes where this one agrees on 0.98 (docs/results.md).

In imagination the state is the model's learned state (``RolloutView.state``), so a model without a state head
cannot be scored this way; its block and goal are what the imagined frames show the estimator.
"""
from __future__ import annotations

import functools

import numpy as np

from sc3_jax.core.errors import UserError

CRITERION = "success"
RADIUS = 0.03  # m: the simulator's success radius (the block's centre within it of the goal's)
REST_Z = 0.03  # m: the block's centre below this rests on the table (0.02 when it does)
LIFT_Z = 0.05  # m: above this at some earlier frame, the block was lifted
GRIP = 10  # the state's gripper command: 1 open, -1 closed


def placed_frames(estimates: np.ndarray, gripper: np.ndarray) -> np.ndarray:
    """bool [T]: frame t shows the block placed -- estimates [T, 5] (block xyz, goal xy, metres), gripper [T] (the
    jaw command, > 0 open). Lifted means lifted at or before t."""
    e = np.asarray(estimates, np.float64)
    near = np.linalg.norm(e[:, :2] - e[:, 3:5], axis=1) < RADIUS
    lifted = np.maximum.accumulate(e[:, 2]) > LIFT_Z
    return near & (e[:, 2] < REST_Z) & lifted & (np.asarray(gripper) > 0)


@functools.cache
def _estimator():
    import jax
    from sc3_jax.benchmarks.so101 import zoo
    net = zoo.load_params(zoo.ZOO_DIR / zoo.ZOO["so_full"].weights)
    return jax.jit(lambda images, state: zoo.estimate(net, images, state))


def block_placed(view) -> dict[str, bool]:
    """The scorer: ``{"success": placed in some frame}`` for a ``RolloutView`` (its first view, the workspace
    camera, and its state [T, 14])."""
    if view.state is None:
        raise UserError("the scorer block_placed reads the robot state (the jaw, the end effector): score with a "
                        "world model that has a learned state head, or use scorer:block_at_goal")
    frames, state = np.asarray(view.frames[0]), np.asarray(view.state, np.float32)
    if len(state) != len(frames) or state.ndim != 2 or state.shape[1] <= GRIP + 3:
        raise UserError(f"block_placed needs SO-101's 14-D state at every frame; got state {state.shape} for "
                        f"{len(frames)} frames")
    est = np.asarray(_estimator()(frames, state))
    return {CRITERION: bool(placed_frames(est, state[:, GRIP]).any())}
