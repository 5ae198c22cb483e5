"""The world-model recipe's conditions: pose conditioning (one function for training windows and rollouts, withheld
when actions are targets), context noise (never on a loss target), and the gripper label's single meaning."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.model import flow, modes
from sc3_jax.rollout import imagination_state
from sc3_jax.core.config import DataConfig, FlowConfig, ModelConfig
from sc3_jax.data import norm_stats
from sc3_jax.data import pipeline as P
from sc3_jax.data import synthetic as S
from sc3_jax.data.action_space import DELTA_EE
from sc3_jax.model import dit

CFG = ModelConfig(dim=32, depth=2, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64, rope_axes_dim=(4, 2, 2),
                  patch_size=4, pose_conditioning=True, context_noise=True)
GRID = (2, 2)
V, K, T, P_, D = 3, 2, 3, 4, 48


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("episodes")
    return S.generate(root, num_episodes=3, length=30, image_size=(16, 16), seed=4, progress=False)


def _batch(key, B=4):
    ks = jax.random.split(key, 3)
    video = jax.random.normal(ks[0], (B, V, K + T, P_, D))
    actions = jax.random.normal(ks[1], (B, T, 7))
    pose = jax.random.normal(ks[2], (B, T + 1, 7))
    return video, actions, pose


def _params(key):
    p = dit.init_params(CFG, D, key, GRID)
    # non-zero output heads, so outputs depend on every input
    return jax.tree.map(lambda x: x + 0.05 * jax.random.normal(jax.random.key(1), x.shape), p)


# -- pose condition: one function for training and rollouts --------------------------------------------------------
def test_window_pose_equals_integrated_commanded_actions(store):
    """The pipeline's pose condition is frame K-1's pose integrated with the window's actions -- exactly what a
    rollout computes with imagination_state.frame_poses -- and follows the recorded poses of the episode."""
    stats = norm_stats.NormStats.from_store(store)
    for pseudo_p in (0.0, 1.0):
        cfg = DataConfig(path=str(store.root), image_size=(16, 16), batch_size=8, context_frames=2, future_frames=4,
                         strides=(1, 2), pseudo_action_prob=pseudo_p, seed=5)
        b = P.make_dataset(cfg, store, stats)[0]
        for k in range(8):
            ep = store.load(store.episode_ids()[int(b["episode"][k])])
            s, t0 = int(b["stride"][k]), int(b["start"][k])
            idx = P.window_frame_indices(t0, s, 2, 4)
            raw_actions = stats.denormalize(b["actions"][k])
            start = P.start_pose(ep.actions, ep.ee_pose, int(idx[1]))
            rollout_pose = np.asarray(imagination_state.frame_poses(jnp.asarray(start), jnp.asarray(raw_actions),
                                                                    DELTA_EE))
            got = b["pose"][k] * stats.pose_std + stats.pose_mean
            np.testing.assert_allclose(got, rollout_pose, atol=2e-5)
            # the integrated xyz follows the recorded poses (pseudo: exactly; recorded: up to clipping at walls)
            err = np.abs(got[:, :3] - ep.ee_pose[idx[1:], :3])
            assert np.median(err) < 1e-5 if pseudo_p else np.median(err) < 5e-3
            # gripper entry = the command in force, never the measured gap
            np.testing.assert_allclose(got[1:, 6], ep.actions[idx[2:] - 1, 6], atol=1e-6)


def test_gripper_label_has_one_meaning(store):
    """Pseudo-actions and recorded actions of the same window carry the same gripper command."""
    ep = store.load(store.episode_ids()[0])
    for stride in (1, 2, 3):
        rec = P.window_actions(ep.actions, ep.ee_pose, 0, stride, 2, 4, pseudo=False, space=DELTA_EE)
        pse = P.window_actions(ep.actions, ep.ee_pose, 0, stride, 2, 4, pseudo=True, space=DELTA_EE)
        np.testing.assert_array_equal(rec[:, 6], pse[:, 6])
    # the measured gap differs from the command on this data (otherwise the test above proves nothing)
    assert np.abs(ep.ee_pose[1:, 6] - ep.actions[:-1, 6]).max() > 1e-3


def test_future_poses_are_withheld_when_actions_are_targets():
    params = _params(jax.random.key(0))
    video, actions, pose = _batch(jax.random.key(2))
    B = video.shape[0]
    other = pose.at[:, 1:].add(3.0)  # different future poses, same frame K-1 pose

    def out(mode, p):
        vn, an = modes.fixed(mode, B, V, K, T)
        inp = dit.Inputs(video, actions, jnp.where(vn, 0.5, 0.0), vn, jnp.where(an, 0.5, 0.0), an,
                         jnp.ones((B,), jnp.int32), pose=p, context_level=jnp.zeros((B,)))
        return dit.apply(params, CFG, inp, GRID)

    ov, oa = out(modes.ID, pose)
    ov2, oa2 = out(modes.ID, other)
    np.testing.assert_array_equal(oa, oa2)  # inverse mode cannot read its answer off the poses
    fv, _ = out(modes.FD, pose)
    fv2, _ = out(modes.FD, other)
    assert float(jnp.abs(fv - fv2).max()) > 1e-3  # forward mode does see them
    with pytest.raises(ValueError, match="Inputs.pose"):
        out(modes.FD, None)


# -- context noise ---------------------------------------------------------------------------------------------------
def test_noise_context_touches_only_context_frames():
    video, _, _ = _batch(jax.random.key(3))
    level = jnp.array([0.0, 0.3, 1.0, 0.5])
    out = flow.noise_context(video, level, jax.random.key(4), K)
    np.testing.assert_array_equal(out[:, :, K:], video[:, :, K:])
    np.testing.assert_array_equal(out[0], video[0])  # level 0: unchanged
    assert float(jnp.abs(out[1:, :, :K] - video[1:, :, :K]).min()) > 0


@pytest.mark.slow  # 25-55 s: kept out of the default run's 15 minutes (CI runs -m slow too)
def test_context_noise_never_reaches_a_loss_target(monkeypatch):
    """With context noise on, the model sees noised context frames, but every loss target is the clean frame (and
    clean future conditions -- CVI's kept view, ID's frames -- are never noised)."""
    params = _params(jax.random.key(5))
    video, actions, pose = _batch(jax.random.key(6), B=8)
    seen = {}
    real_predict, real_loss = flow.predict, flow.masked_loss

    def spy_predict(params, cfg, inp, grid, *a, **kw):
        seen["inp"] = inp
        return real_predict(params, cfg, inp, grid, *a, **kw)

    def spy_loss(pred_v, pred_a, target_v, target_a, *a, **kw):
        seen["targets"] = (target_v, target_a)
        return real_loss(pred_v, pred_a, target_v, target_a, *a, **kw)

    monkeypatch.setattr(flow, "predict", spy_predict)
    monkeypatch.setattr(flow, "masked_loss", spy_loss)
    fcfg = FlowConfig(context_noise_max=0.5)
    flow.loss(params, CFG, video, actions, jnp.ones((8,), jnp.int32), jax.random.key(7), (0.4, 0.3, 0.3), GRID,
              fcfg, pose=pose)
    inp = seen["inp"]
    np.testing.assert_array_equal(seen["targets"][0], video[:, :, K:])
    np.testing.assert_array_equal(seen["targets"][1], actions)
    clean_future = ~inp.video_noisy[:, :, K:]
    np.testing.assert_array_equal(jnp.where(clean_future[..., None, None], inp.video[:, :, K:], 0),
                                  jnp.where(clean_future[..., None, None], video[:, :, K:], 0))
    assert inp.context_level is not None and float(inp.context_level.max()) <= 0.5
    noised = inp.context_level > 0
    assert bool(noised.any())
    assert float(jnp.abs(inp.video[noised][:, :, :K] - video[noised][:, :, :K]).min()) > 0
    with pytest.raises(ValueError, match="model.context_noise"):
        flow.loss(params, ModelConfig(**{**CFG.__dict__, "context_noise": False}), video, actions,
                  jnp.ones((8,), jnp.int32), jax.random.key(7), (1, 0, 0), GRID, fcfg, pose=pose)


def test_sampler_returns_the_given_context_and_uses_the_level():
    params = _params(jax.random.key(8))
    video, actions, pose = _batch(jax.random.key(9), B=2)
    vn, an = modes.fixed(modes.FD, 2, V, K, T)
    stride = jnp.ones((2,), jnp.int32)
    a, _ = flow.sample(params, CFG, video, actions, stride, vn, an, jax.random.key(1), 2, GRID, pose=pose,
                       context_noise=0.2, cache="none")
    b, _ = flow.sample(params, CFG, video, actions, stride, vn, an, jax.random.key(1), 2, GRID, pose=pose,
                       context_noise=0.0, cache="none")
    np.testing.assert_array_equal(a[:, :, :K], video[:, :, :K])
    assert float(jnp.abs(a[:, :, K:] - b[:, :, K:]).max()) > 1e-4
