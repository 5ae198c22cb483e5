import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.model import flow, modes
from sc3_jax.core.config import ModelConfig, load_config
from sc3_jax.model import dit, layers, tokenizer

B, V, K, T, H = 2, 3, 2, 4, 16


SHORTCUTS = dict(anchor_conditioning=True, action_to_frames=True, action_reads_frames=True)


def _setup(**kw):
    cfg = ModelConfig(dim=64, depth=2, num_heads=4, num_kv_heads=2, head_dim=32, mlp_dim=128, **kw)
    tok = tokenizer.PixelPatchTokenizer(4)
    params = dit.init_params(cfg, tok.token_dim, jax.random.key(0), tok.grid((H, H)))
    # non-zero output weights so outputs depend on everything
    params = jax.tree.map(lambda p: p + 0.05 * jax.random.normal(jax.random.key(1), p.shape), params)
    frames = jax.random.randint(jax.random.key(2), (B, V, K + T, H, H, 3), 0, 256).astype(jnp.uint8)
    video = tok.encode(frames)
    actions = jax.random.normal(jax.random.key(3), (B, T, 7))
    return cfg, tok, params, frames, video, actions, tok.grid((H, H))


def test_tokenizer_round_trip_exact():
    tok = tokenizer.PixelPatchTokenizer(4)
    frames = jax.random.randint(jax.random.key(0), (2, 5, 16, 12, 3), 0, 256).astype(jnp.uint8)
    tokens = tok.encode(frames)
    assert tokens.shape == (2, 5, 12, 48)
    assert np.array_equal(tokenizer.to_uint8(tok.decode(tokens, (16, 12))), frames)
    x = tokenizer.to_unit(frames)
    assert np.array_equal(tok.decode(tok.encode(x), (16, 12)), x)
    # patch (0, 1) holds the pixels rows 0:4, cols 4:8 in (pi, pj, c) order
    assert np.array_equal(tokens[0, 0, 1], x[0, 0, 0:4, 4:8].reshape(-1))
    with pytest.raises(ValueError, match="multiple of patch size"):
        tok.grid((15, 16))


def test_param_axes_cover_every_param():
    cfg = ModelConfig(**SHORTCUTS)
    params = dit.init_params(cfg, 48, jax.random.key(0), (4, 4))
    axes = dit.param_axes(cfg, 48, (4, 4))
    flat_p = jax.tree.leaves(params)
    flat_a = jax.tree.leaves(axes, is_leaf=lambda a: type(a) is tuple)
    assert len(flat_p) == len(flat_a)
    for p, a in zip(flat_p, flat_a):
        assert len(a) == p.ndim and all(isinstance(n, str) for n in a)


def test_paper_scale_abstract_shapes():
    cfg = load_config("paper")
    tok = tokenizer.make_tokenizer(cfg.model)
    shapes = jax.eval_shape(lambda: dit.init_params(cfg.model, tok.token_dim, jax.random.key(0)))
    n = dit.count_params(shapes)
    assert 1.8e9 < n < 2.4e9, n


def test_gqa_attention_matches_reference():
    q = jax.random.normal(jax.random.key(0), (2, 5, 4, 8))
    k = jax.random.normal(jax.random.key(1), (2, 7, 2, 8))
    v = jax.random.normal(jax.random.key(2), (2, 7, 2, 8))
    out = layers.attention(q, k, v)
    kk, vv = jnp.repeat(k, 2, axis=2), jnp.repeat(v, 2, axis=2)  # query head h uses kv head h // 2
    w = jax.nn.softmax(jnp.einsum("bnhd,bmhd->bhnm", q, kk) / math.sqrt(8), axis=-1)
    ref = jnp.einsum("bhnm,bmhd->bnhd", w, vv)
    np.testing.assert_allclose(out, ref, atol=1e-5)
    np.testing.assert_allclose(out, jax.nn.dot_product_attention(q, k, v), atol=1e-5)
    mask = jax.random.bernoulli(jax.random.key(3), 0.7, (1, 1, 5, 7)).at[..., 0].set(True)
    np.testing.assert_allclose(layers.attention(q, k, v, mask), jax.nn.dot_product_attention(q, k, v, mask=mask),
                               atol=1e-5)


def test_mrope_sections_and_relative_positions():
    axis = np.asarray(layers.mrope_axis_index(32, (6, 5, 5)))
    assert [(axis == i).sum() for i in range(3)] == [6, 5, 5]
    assert axis[:6].tolist() == [0, 1, 2, 0, 1, 2]
    # rotary attention scores depend only on position differences
    q = jax.random.normal(jax.random.key(0), (1, 1, 1, 32))
    k = jax.random.normal(jax.random.key(1), (1, 1, 1, 32))

    def score(pq, pk):
        cq, sq = layers.rope_cos_sin(jnp.asarray([[pq]], jnp.float32), 32, (6, 5, 5), 10000.0)
        ck, sk = layers.rope_cos_sin(jnp.asarray([[pk]], jnp.float32), 32, (6, 5, 5), 10000.0)
        return float(jnp.sum(layers.apply_rope(q, cq, sq) * layers.apply_rope(k, ck, sk)))

    assert score([3, 1, 2], [1, 0, 0]) == pytest.approx(score([5, 4, 7], [3, 3, 5]), rel=1e-4)
    assert score([3, 1, 2], [1, 0, 0]) != pytest.approx(score([3, 1, 2], [1, 0, 1]), rel=1e-4)


def test_timestep_embedding_only_on_noisy_tokens():
    cfg, tok, params, frames, video, actions, grid = _setup()
    vn, an = modes.fixed(modes.FD, B, V, K, T)
    zeros = jnp.zeros(vn.shape)
    base = dit.Inputs(video, actions, zeros, vn, jnp.zeros(an.shape), an, jnp.ones(B, jnp.int32))
    # changing t of clean tokens changes nothing; changing t of noisy tokens does
    out0 = dit.apply(params, cfg, base, grid)
    out1 = dit.apply(params, cfg, base._replace(action_t=jnp.full(an.shape, 0.7)), grid)
    out2 = dit.apply(params, cfg, base._replace(video_t=jnp.where(vn, 0.7, 0.0)), grid)
    np.testing.assert_array_equal(out0[0], out1[0])
    assert not np.allclose(out0[0], out2[0])


@pytest.mark.parametrize("mode,prefix", [(modes.FD, "context"), (modes.CVI, "context"), (modes.ID, "context"),
                                         (modes.ID, "video")])
def test_context_cache_matches_uncached(mode, prefix):
    cfg, tok, params, frames, video, actions, grid = _setup(context_attention="causal", **SHORTCUTS)
    vn, an = modes.fixed(mode, B, V, K, T, kept_view=1)
    stride = jnp.asarray([1, 2])
    full = flow.sample(params, cfg, video, actions, stride, vn, an, jax.random.key(5), 3, grid, cache="none")
    cached = flow.sample(params, cfg, video, actions, stride, vn, an, jax.random.key(5), 3, grid, cache=prefix)
    np.testing.assert_allclose(full[0], cached[0], atol=2e-5)
    np.testing.assert_allclose(full[1], cached[1], atol=2e-5)


def test_causal_attention_rule():
    """causal: context -> context only; other clean tokens -> clean only; noisy tokens -> everything."""
    cfg = ModelConfig(context_attention="causal")
    noisy = jnp.asarray([[False, False, True, False, True]])  # tokens 0-1 context, 2 noisy, 3 clean, 4 noisy
    m = np.asarray(dit._attention_mask(cfg, noisy, n_ctx=2))[0, 0]
    np.testing.assert_array_equal(m, [[1, 1, 0, 0, 0], [1, 1, 0, 0, 0], [1, 1, 1, 1, 1], [1, 1, 0, 1, 0],
                                      [1, 1, 1, 1, 1]])
    assert dit._attention_mask(ModelConfig(), noisy, 2) is None


def test_causal_context_does_not_see_targets():
    """Under causal context attention, the context's keys/values do not depend on the future tokens."""
    cfg, tok, params, frames, video, actions, grid = _setup(context_attention="causal", **SHORTCUTS)
    vn, an = modes.fixed(modes.FD, B, V, K, T)
    inp = dit.Inputs(video, actions, jnp.where(vn, 0.5, 0.0), vn, jnp.zeros(an.shape), an, jnp.ones(B, jnp.int32))
    kv1 = dit.encode_context(params, cfg, inp, grid)
    kv2 = dit.encode_context(params, cfg, inp._replace(video=video.at[:, :, K:].add(1.0), actions=actions * 2), grid)
    np.testing.assert_array_equal(kv1[0], kv2[0])
    with pytest.raises(ValueError, match="causal"):
        dit.encode_context(params, ModelConfig(**SHORTCUTS), inp, grid)


def test_shortcut_features():
    """anchor_conditioning sees the 3x3 neighbourhood; action_reads_frames sees frame differences."""
    frame = jnp.arange(2 * 1 * 4 * 1, dtype=jnp.float32).reshape(2, 1, 4, 1)  # 2x2 grid, 1 feature
    nb = dit._neighbourhood(frame, (2, 2))
    assert nb.shape == (2, 1, 4, 9)
    # patch (0, 0): centre is index 4 of the 3x3 block, its right neighbour (0, 1) index 5, below (1, 0) index 7
    np.testing.assert_array_equal(nb[0, 0, 0], [0, 0, 0, 0, 0, 1, 0, 2, 3])
    cfg, tok, params, frames, video, actions, grid = _setup(**SHORTCUTS)
    vn, an = modes.fixed(modes.ID, B, V, K, T)
    inp = dit.Inputs(video, actions, jnp.zeros(vn.shape), vn, jnp.where(an, 0.5, 0.0), an, jnp.ones(B, jnp.int32))
    emb = lambda i, c=cfg: dit._embed(params, c, i, grid, 0)  # noqa: E731
    x0 = emb(inp)
    # action token embeddings move with frame K's content (it is a frame difference for actions 0 and 1) ...
    x1 = emb(inp._replace(video=inp.video.at[:, :, K].add(0.5)))
    assert not np.allclose(x0[:, -T:], x1[:, -T:])
    # ... only while the frames are clean (forward mode: future frames noisy, no frame differences read)
    fd_v, fd_a = modes.fixed(modes.FD, B, V, K, T)
    fd = inp._replace(video_noisy=fd_v, action_noisy=fd_a, action_t=jnp.zeros(fd_a.shape))
    np.testing.assert_allclose(emb(fd)[:, -T:], emb(fd._replace(video=fd.video.at[:, :, K].add(0.5)))[:, -T:],
                               atol=1e-6)
    # ... but not with a change of every frame by the same amount (differences unchanged, anchor moves)
    x2 = emb(inp._replace(video=inp.video.at[:, :, K - 1:].add(0.5)))
    np.testing.assert_allclose(x0[:, -T:], x2[:, -T:], atol=1e-5)
    # future frames see the anchor frame (context tokens are untouched by every shortcut)
    x3 = emb(inp._replace(video=inp.video.at[:, :, K - 1].add(0.5)))
    n_ctx = V * K * grid[0] * grid[1]
    assert not np.allclose(x0[:, n_ctx:-T], x3[:, n_ctx:-T])
    plain = dit.init_params(ModelConfig(dim=64, depth=2, num_heads=4, num_kv_heads=2, head_dim=32, mlp_dim=128), 48,
                            jax.random.key(0))
    assert set(params) - set(plain) == {"anchor_in", "action_to_frames", "frames_to_action"}


def test_weight_decay_only_on_weight_matrices():
    mask = dit.decay_mask(ModelConfig(**SHORTCUTS), 48, (4, 4))
    assert mask["layers"]["wq"] and mask["layers"]["w_down"] and mask["proj_out"]["w"] and mask["action_in"]["w"]
    assert not any([mask["layers"]["attn_norm"], mask["layers"]["q_norm"], mask["final_norm"], mask["proj_in"]["b"],
                    mask["action_in"]["b"], mask["action_out"]["b"], mask["view_embed"],
                    mask["action_modality_embed"]])
