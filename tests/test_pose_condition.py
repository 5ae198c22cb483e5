"""The conditioning contract (DESIGN.md): every future frame is conditioned on where the robot is commanded to be, in
the robot's units, by one computation in training windows and rollouts: velocity commands integrated (with the data's
dt and gain, clipped to the recorded range) from the *measured* state at the last context frame into the recorded
entries they move -- never a displacement from zero that restarts every window."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.rollout import imagination_state, rollout
from sc3_jax.core.config import load_config, replace
from sc3_jax.data import pipeline as P
from sc3_jax.data.action_space import ActionSpace, fit_measured
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.core.errors import UserError

FPS = 10.0
SPACE = ActionSpace("velocity", 4, ("dx", "dy", "dz", "gripper"), (3,))  # SO-101's: the gripper a target
GAIN = 0.25  # metres per second per unit (SO-101: 0.025 m a step at 10 Hz)


def _episode(rng, length, order, gain=GAIN):
    """SO-101-like: joints that wander, a gripper measurement, and an end effector the xyz commands move (with some
    lag noise); ``order`` places the state's 6 entries."""
    a = np.concatenate([rng.uniform(-1, 1, (length, 3)), rng.integers(0, 2, (length, 1))], 1).astype(np.float32)
    ee = np.array([0.2, 0.0, 0.1]) + np.concatenate([np.zeros((1, 3)), np.cumsum(a[:-1, :3] * gain / FPS, 0)])
    ee += rng.normal(0, 0.0005, ee.shape)  # half a millimetre of measurement noise
    joints = np.cumsum(rng.normal(0, 0.05, (length, 2)), 0)
    grip = 2 * np.concatenate([[a[0, 3]], a[:-1, 3]]) - 1
    state = np.concatenate([joints, grip[:, None], ee], 1)[:, order]
    return a, state.astype(np.float32)


def _store(root, n=3, length=40, seed=0):
    rng = np.random.default_rng(seed)
    s = EpisodeStore(root, views=["cam"], fps=FPS, image_size=(8, 8), create=True, action_space=SPACE, state_dim=6,
                     has_pose=False)
    for i in range(n):
        a, state = _episode(rng, length, np.arange(6))
        s.write(Episode(f"ep{i}", {"cam": rng.integers(0, 256, (length, 8, 8, 3), dtype=np.uint8)}, a, None,
                        "pick", {}, state))
    return s


@settings(max_examples=25, deadline=None)
@given(perm=st.permutations(list(range(6))), gain=st.floats(0.05, 2.0) | st.floats(-2.0, -0.05))
def test_the_fit_finds_which_recorded_entries_the_commands_move_and_at_what_gain(perm, gain):
    rng = np.random.default_rng(1)
    eps = [_episode(rng, 60, np.argsort(perm), gain) for _ in range(3)]  # original entry q lands at perm[q]
    space = fit_measured(SPACE, eps, 1 / FPS)
    ee_at = [perm[3], perm[4], perm[5]]
    assert space.measured == (*ee_at, -1)  # dx -> ee_x, ...; the gripper target moves nothing by integration
    np.testing.assert_allclose(space.gain[:3], gain, rtol=0.1)
    assert fit_measured(space, eps, 1 / FPS) is space  # stated: kept as it is


def test_a_window_starts_at_the_measured_end_effector_not_at_zero(tmp_path):
    store = _store(tmp_path / "s")
    stats = NormStats.from_store(store)
    sp = stats.action_space
    assert sp.measured == (3, 4, 5, -1) and sp.low and sp.high
    ep = store.load("ep0")
    acts = P.window_actions(ep.actions, None, 5, 1, 2, 6, False, sp)
    pose = P.window_pose(sp, ep.actions, None, ep.state, 6, acts, 1 / FPS)
    np.testing.assert_allclose(pose[0, :3], ep.state[6, 3:6], atol=1e-6)  # where the arm is, in metres
    np.testing.assert_allclose(pose[1:, :3], ep.state[7:13, 3:6], atol=0.01)  # and where the commands take it
    # normalised by the measured entries' spread over the store: within a window it moves, not 0.01 around a constant
    z = stats.normalize_pose(pose)
    assert np.ptp(z[:, :3], axis=0).max() > 0.1
    # the old conditioning (no mapping): a displacement from zero, and exactly that for every window
    old = ActionSpace("velocity", 4, targets=(3,))
    np.testing.assert_array_equal(P.window_pose(old, ep.actions, None, ep.state, 6, acts, 0.1)[0, :3], 0)


@pytest.mark.parametrize("stride", [1, 2])
def test_the_pose_a_training_window_hands_the_model_is_the_one_a_rollout_computes(tmp_path, stride):
    """A recorded episode both ways: the pipeline's window (frame K-1 = episode frame t) and a rollout started at t
    with the same recorded actions, through rollout.initial_state, chunk_actions and the jnp frame_poses."""
    store = _store(tmp_path / "s", length=60)
    stats = NormStats.from_store(store)
    K, T = 2, 6
    cfg = replace(load_config("tiny"), model=dict(action_dim=4, num_views=1, pose_conditioning=True,
                                                  action_sum="pose"),
                  data=dict(views=("cam",), image_size=(8, 8), context_frames=K, future_frames=T, strides=(stride,),
                            batch_size=4, pseudo_action_prob=0.0),
                  rollout=dict(policy_chunk=T, keep_frames=4, control_hz=FPS / stride, policy_hz=FPS / stride))
    batch = P.make_dataset(cfg.data, store, stats)[0]
    ro = rollout.Rollout(cfg, stats, data_fps=FPS, num_chunks=1)
    assert ro.spec.stride == stride
    for k in range(4):
        ep = store.load(store.episode_ids()[int(batch["episode"][k])])
        t = int(batch["start"][k]) + stride * (K - 1)  # the window's last context frame
        s0 = rollout.initial_state(ep, ro.spec, t)
        model_actions = rollout.chunk_actions(ep.actions[t:], ro.spec)[0]  # [T, A] at the model's rate
        pose = np.asarray(imagination_state.frame_poses(s0, model_actions, ro.spec.action_space, ro.spec.model_dt))
        np.testing.assert_allclose(stats.normalize_pose(pose), batch["pose"][k], atol=2e-5)
        np.testing.assert_allclose(stats.normalize(model_actions), batch["actions"][k], atol=2e-5)


def test_the_imagined_state_stays_inside_the_recorded_range_in_both_twins():
    sp = ActionSpace("velocity", 2, gain=(1.0, 1.0), measured=(0, 1), low=(-1.0, 0.0), high=(1.0, 0.5))
    a = np.ones((8, 2), np.float32)
    np_states = sp.integrate(np.zeros(2, np.float32), a, dt=0.5)
    jnp_states = np.asarray(imagination_state.frame_poses(np.zeros(2, np.float32), a, sp, 0.5))
    np.testing.assert_allclose(np_states[-1], [1.0, 0.5])
    np.testing.assert_allclose(np_states, jnp_states, atol=1e-6)
    # a step back from the wall moves at once (per-step clipping, not a clipped running sum)
    back = sp.integrate(np_states[-1], -np.ones((1, 2), np.float32), dt=0.5)
    np.testing.assert_allclose(back[-1], [0.5, 0.0])


def test_a_mapping_that_does_not_fit_the_space_is_one_line():
    for bad in (dict(measured=(0, 1)), dict(gain=(1.0,) * 4, kind="absolute"), dict(low=(0.0,) * 4),
                dict(gain=(math.nan,) * 4)):
        kw = {"kind": "velocity", "dim": 4, "targets": (3,) if bad.get("kind", "velocity") == "velocity" else (),
              **bad}
        with pytest.raises(UserError) as e:
            ActionSpace(**kw)
        assert "\n" not in str(e.value)
    d = ActionSpace("velocity", 4, targets=(3,), measured=(3, 4, 5, -1), gain=(0.25,) * 4).to_dict()
    assert ActionSpace.from_dict(d) == ActionSpace("velocity", 4, targets=(3,), measured=(3, 4, 5, -1),
                                                   gain=(0.25,) * 4)


def test_a_fine_tune_from_a_model_that_integrated_from_zero_conditions_on_the_measured_state_in_its_action_units(
        tmp_path):
    from sc3_jax.train.train import reconditioned

    store = _store(tmp_path / "s")
    old = NormStats(np.full(4, 0.1), np.full(4, 2.0), action_space=SPACE)  # the pose from zero: nothing measured
    new = reconditioned(old, store)
    assert new.action_space.measured == (3, 4, 5, -1)  # the end effector the commands move, fitted from the store
    np.testing.assert_array_equal(new.mean, old.mean)  # the params' action units stay
    np.testing.assert_array_equal(new.std, old.std)
    assert not np.allclose(new.pose_std, 1.0)  # the pose statistics are the measured entries'
    assert reconditioned(new, store) is new  # a model already conditioned on the measured state keeps its own
