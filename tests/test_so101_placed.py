"""`--scorer sc3_jax.benchmarks.so101.placed:block_placed`: the simulator's success rule (lifted, at rest within the
radius of the goal, the jaw open) on the zoo estimator's block and goal: the rule on estimates, and the refusals
(the scorer on the simulator's real episodes: tests/test_so101_env.py)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.benchmarks.so101.placed import LIFT_Z, RADIUS, REST_Z, block_placed, placed_frames
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.scorers import RolloutView

GOAL = np.array([0.25, 0.05])


def _pick_and_place(offset: np.ndarray, lift: float, rest: float, t: int = 12):
    """Estimates [t, 5] of a block lifted to ``lift`` then set down at ``rest`` height, ``offset`` from the goal."""
    start = GOAL + np.array([-0.08, 0.03])
    z = np.r_[np.full(3, 0.02), np.full(t - 6, lift), np.full(3, rest)]
    xy = np.r_[np.repeat(start[None], 3, 0), np.repeat((GOAL + offset)[None], t - 3, 0)]
    return np.c_[xy, z, np.repeat(GOAL[None], t, 0)]


@settings(max_examples=60, deadline=None)
@given(r=st.floats(0.0, 0.95), angle=st.floats(0, 2 * np.pi), lift=st.floats(LIFT_Z + 0.005, 0.12),
       rest=st.floats(0.015, REST_Z - 0.002))
def test_a_lifted_block_set_down_on_the_goal_with_the_jaw_open_is_placed_and_each_condition_is_needed(r, angle, lift,
                                                                                                      rest):
    direction = np.array([np.cos(angle), np.sin(angle)])
    off = r * RADIUS * direction
    est, jaw = _pick_and_place(off, lift, rest), np.r_[-np.ones(11), 1.0]
    assert placed_frames(est, jaw).tolist() == [False] * 11 + [True]
    assert not placed_frames(est, -np.ones(12)).any()                    # the jaw still closed
    assert not placed_frames(_pick_and_place(off, LIFT_Z - 0.005, rest), jaw).any()   # never lifted
    assert not placed_frames(_pick_and_place(off, lift, REST_Z + 0.005), jaw).any()   # still in the air
    assert not placed_frames(_pick_and_place(1.05 * RADIUS * direction, lift, rest), jaw).any()  # beside the goal


def test_block_placed_refuses_a_rollout_without_the_robot_state_in_one_line():
    frames = np.zeros((2, 3, 80, 80, 3), np.uint8)
    with pytest.raises(UserError, match="learned state head"):
        block_placed(RolloutView("x", frames))
    with pytest.raises(UserError, match="14-D state at every frame"):
        block_placed(RolloutView("x", frames, state=np.zeros((2, 14), np.float32)))
