"""Memory in the context (data.anchor): the episode's first frame kept in front of every window's context at its
true time. The anchor's tokens sit ``anchor_gap`` data frames before the first context frame; training windows carry
episode frame 0 and the gap; a closed-loop rollout keeps the first observation, at a gap that grows by the kept frames
of every chunk, and without an anchor nothing changes."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_rollout import FPS, STATS, _cfg, _ics, _params

from sc3_jax.model import flow, modes
from sc3_jax.rollout import rollout
from sc3_jax.core.config import replace
from sc3_jax.model import dit


def test_the_anchor_tokens_sit_their_gap_before_the_first_context_frame():
    V, K, T, grid = 2, 3, 2, (2, 2)
    stride, gap = jnp.asarray([1, 2]), jnp.asarray([5, 0])
    plain = dit.positions(stride, V, K + T, grid, T, K)
    anchored = dit.positions(stride, V, K + T, grid, T, K, gap)
    frame = np.asarray(jnp.broadcast_to(jnp.arange(V * K * 4) // 4 % K, (V * K * 4,)))  # context token -> frame
    first = np.concatenate([frame == 0, np.zeros(anchored.shape[1] - len(frame), bool)])
    np.testing.assert_array_equal(anchored[:, ~first], plain[:, ~first])  # every other token where it was
    np.testing.assert_allclose(anchored[:, first, 0], [[1 - 5] * first.sum(), [2 - 0] * first.sum()])
    np.testing.assert_array_equal(anchored[:, first, 1:], plain[:, first, 1:])  # rows and columns unchanged


@pytest.mark.slow  # 25-55 s: kept out of the default run's 15 minutes (CI runs -m slow too)
def test_the_model_reads_where_in_time_the_anchor_sits():
    cfg = _cfg()
    params = _params(cfg)
    B, V, K, T = 2, 3, 3, 4  # one anchor + 2 context frames
    rng = np.random.default_rng(0)
    video = jnp.asarray(rng.normal(size=(B, V, K + T, 1, 192)), jnp.float32)  # 8x8 frames, patch 8: 1 token
    actions = jnp.asarray(rng.normal(size=(B, T, 7)), jnp.float32)
    vn, an = modes.fixed(modes.FD, B, V, K, T)

    def run(gap):
        return flow.sample(params, cfg.model, video, actions, jnp.ones(B, jnp.int32), vn, an, jax.random.key(0), 2,
                           (1, 1), anchor_gap=gap)[0]

    near, far = run(jnp.asarray([0, 0])), run(jnp.asarray([40, 40]))
    assert not np.allclose(near, far)  # where in time the anchor sits is read
    # one stride before the first context frame is where frame 0 sits without an anchor: the same numbers
    np.testing.assert_allclose(run(jnp.asarray([1, 1])), run(None), rtol=1e-6, atol=1e-6)


@pytest.mark.slow  # 25-55 s: kept out of the default run's 15 minutes (CI runs -m slow too)
def test_a_closed_loop_keeps_the_first_observation_at_a_growing_gap(monkeypatch):
    cfg = replace(_cfg(), data=dict(anchor=True))
    ro = rollout.Rollout(cfg, STATS, data_fps=FPS, num_chunks=3, cache=False)
    assert ro.spec.anchor == 1
    params = _params(cfg)
    ics = _ics(cfg, n=1)
    fns = ro.chunk_fns
    carry = fns.init(ics.frames[0], ics.state[0], np.zeros(0, np.float32))
    np.testing.assert_array_equal(carry.anchor, carry.context[:, :1])  # the first observation
    gaps = []
    real_sample = flow.sample

    def spy(*args, anchor_gap=None, **kwargs):
        gaps.append(np.asarray(anchor_gap))
        return real_sample(*args, anchor_gap=anchor_gap, **kwargs)

    monkeypatch.setattr(flow, "sample", spy)
    key = np.asarray(rollout.episode_keys(0, 1))[0]
    acts = jnp.zeros((cfg.rollout.policy_chunk, 7))
    for chunk in range(3):  # eagerly, so the gap is a number: l = 3 kept frames of the data's stride per chunk
        gaps.clear()
        new, _ = fns.model_step(params, ro.norm, carry, acts, key, jnp.float32(math.inf))
        assert [int(g[0]) for g in gaps] == [3 * ro.spec.stride * chunk] * 2  # forward and inverse dynamics
        np.testing.assert_array_equal(new.anchor, carry.anchor)  # kept whatever the context becomes
        assert not np.array_equal(new.context, carry.context)
        carry = new
    monkeypatch.setattr(flow, "sample", real_sample)
    out = ro.run_offline(ro.place_params(params), _ics(cfg, n=2), np.zeros((2, 3, 4, 7), np.float32),
                         rollout.episode_keys(0, 2), math.inf)
    assert out["frames"].shape == (2, 3, 9, 8, 8, 3)


def test_training_windows_carry_the_episode_first_frame_and_the_gap(tmp_path):
    from sc3_jax.data import pipeline as P
    from sc3_jax.data.norm_stats import NormStats
    from sc3_jax.data.synthetic import generate

    store = generate(tmp_path / "s", 2, length=24, image_size=(8, 8), progress=False)
    cfg = replace(_cfg(), data=dict(anchor=True, path=str(tmp_path / "s"), batch_size=4, pseudo_action_prob=0.0))
    stats = NormStats.from_store(store)
    b = P.make_dataset(cfg.data, store, stats)[0]
    assert b["frames"].shape[2] == 1 + cfg.data.context_frames + cfg.data.future_frames
    for k in range(4):
        ep = store.load(store.episode_ids()[int(b["episode"][k])])
        assert int(b["anchor_gap"][k]) == int(b["start"][k])
        np.testing.assert_array_equal(b["frames"][k][:, 0], np.stack([ep.frames[v][0] for v in cfg.data.views]))


def test_a_self_forced_window_keeps_the_anchor_and_moves_its_gap_with_the_chunk():
    """With data.anchor, a picked self-forced sample keeps episode frame 0 as its token frame 0, its gap grows by
    shift x stride data frames (the rollout's next chunk), its context is the one-step prediction made with the
    anchor in view; an unpicked one is the first window with its gap unchanged."""
    from test_self_forcing import GRID, K, MCFG, T, V, _extended, _params
    from sc3_jax.core.config import FlowConfig
    B, shift = 6, 2
    params = _params(jax.random.key(0))
    video, actions, pose = _extended(jax.random.key(2), B, shift)
    anchor = jax.random.normal(jax.random.key(9), video[:, :, :1].shape)
    video = jnp.concatenate([anchor, video], axis=2)  # [B, V, 1 + K + T + shift]
    stride, gap = jnp.asarray([1, 2, 1, 2, 1, 2]), jnp.asarray([4, 0, 7, 2, 5, 1])
    eligible, rng = jnp.ones((B,), bool), jax.random.key(3)
    v2, a2, p2, g2, picked = jax.jit(lambda p: flow.self_forced_window(
        p, MCFG, video, actions, stride, rng, GRID, FlowConfig(self_forcing=0.5), shift, eligible, pose, gap))(params)
    picked = np.asarray(picked)
    assert picked.any() and not picked.all(), "this key picks all or none: choose another"
    vn, an = modes.fixed(modes.FD, B, V, 1 + K, T)
    predicted, _ = jax.jit(lambda p: flow.sample(p, MCFG, video[:, :, :1 + K + T], actions[:, :T], stride, vn, an,
                                                 jax.random.split(rng)[1], 1, GRID, cache="none",
                                                 pose=pose[:, :T + 1], anchor_gap=gap))(params)
    fed = jnp.concatenate([video[:, :, 1:1 + K], predicted[:, :, 1 + K:1 + K + shift]], axis=2)[:, :, -K:]
    for b in range(B):
        np.testing.assert_array_equal(v2[b, :, 0], anchor[b, :, 0])
        if picked[b]:
            assert int(g2[b]) == int(gap[b]) + shift * int(stride[b])
            np.testing.assert_allclose(v2[b, :, 1:1 + K], fed[b], rtol=1e-6, atol=1e-6)
            np.testing.assert_array_equal(v2[b, :, 1 + K:], video[b, :, 1 + shift + K:1 + shift + K + T])
            np.testing.assert_array_equal(a2[b], actions[b, shift:])
        else:
            assert int(g2[b]) == int(gap[b])
            np.testing.assert_array_equal(v2[b], video[b, :, :1 + K + T])
    # the prediction saw the anchor: without it (other frame 0) the fed context differs
    other, _ = jax.jit(lambda p: flow.sample(p, MCFG, video[:, :, :1 + K + T].at[:, :, 0].set(0.0), actions[:, :T],
                                             stride, vn, an, jax.random.split(rng)[1], 1, GRID, cache="none",
                                             pose=pose[:, :T + 1], anchor_gap=gap))(params)
    assert float(jnp.abs(other[:, :, 1 + K:] - predicted[:, :, 1 + K:]).max()) > 1e-4


def test_a_train_step_self_forces_with_the_anchor():
    from test_self_forcing import random_batch, small
    from sc3_jax.train import train
    cfg = replace(small(self_forcing=0.5), data=dict(anchor=True))
    batch = random_batch(cfg)
    assert batch["frames"].shape[2] == 1 + cfg.data.context_frames + cfg.data.future_frames + cfg.rollout.keep_frames
    state, metrics = jax.jit(train.make_train_step(cfg))(train.init_state(cfg), batch)
    assert np.isfinite(float(metrics["loss"])) and 0.0 < float(metrics["frac_self_forced"]) <= 1.0
