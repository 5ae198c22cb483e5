"""Memory in the context (data.anchor): the episode's first frame kept in front of every window's context at its
true time. The anchor's tokens sit ``anchor_gap`` data frames before the first context frame; training windows carry
episode frame 0 and the gap; a closed-loop rollout keeps the first observation, at a gap that grows by the kept frames
of every chunk, and without an anchor nothing changes."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_rollout import STATS, _cfg, _ics, _params

from sc3_jax import flow, modes, rollout
from sc3_jax.config import replace
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


def test_a_closed_loop_keeps_the_first_observation_at_a_growing_gap(monkeypatch):
    cfg = replace(_cfg(), data=dict(anchor=True))
    ro = rollout.Rollout(cfg, STATS, num_chunks=3, cache=False)
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


@pytest.mark.parametrize("flag", [dict(flow=dict(self_forcing=0.25))])
def test_what_the_anchor_is_not_wired_into_is_refused(flag):
    from sc3_jax import train
    from sc3_jax.errors import UserError

    with pytest.raises(UserError, match="data.anchor"):
        train.make_train_step(replace(_cfg(), data=dict(anchor=True), **flag))
