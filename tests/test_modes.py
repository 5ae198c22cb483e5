import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.model import flow, modes
from sc3_jax.core.config import ModelConfig
from sc3_jax.model import dit, tokenizer

V, K, T = 3, 2, 4


def test_masks_select_exactly_the_intended_groups():
    mode = jnp.asarray([modes.FD, modes.CVI, modes.CVI, modes.ID])
    kept = jnp.asarray([2, 0, 2, 1])
    vn, an = modes.masks(mode, kept, V, K, T)
    vn, an = np.asarray(vn), np.asarray(an)
    assert vn.shape == (4, V, K + T) and an.shape == (4, T)
    assert not vn[:, :, :K].any(), "context frames are always clean"
    assert vn[0, :, K:].all() and not an[0].any()  # FD: every future frame noisy, actions clean
    for i, kv in ((1, 0), (2, 2)):  # CVI: every future frame but the kept view's
        assert not vn[i, kv].any() and not an[i].any()
        assert all(vn[i, v, K:].all() for v in range(V) if v != kv)
    assert not vn[3].any() and an[3].all()  # ID: only actions


def test_mode_draws_follow_probabilities():
    mode, kept = modes.draw(jax.random.key(0), 20000, V, (0.8, 0.1, 0.1))
    freq = np.bincount(np.asarray(mode), minlength=3) / 20000
    np.testing.assert_allclose(freq, [0.8, 0.1, 0.1], atol=0.015)
    assert set(np.unique(np.asarray(kept))) == {0, 1, 2}
    mode, _ = modes.draw(jax.random.key(0), 5000, V, (0.9, 0.1, 0.0))
    assert not (np.asarray(mode) == modes.ID).any()


def test_loss_ignores_clean_targets():
    """d loss / d target is zero at clean tokens and non-zero at noisy ones, in every mode of a mixed batch."""
    cfg = ModelConfig(dim=64, depth=1, num_heads=2, num_kv_heads=1, head_dim=32, mlp_dim=64)
    params = dit.init_params(cfg, 48, jax.random.key(0))
    B = 6
    video = jax.random.normal(jax.random.key(1), (B, V, K + T, 16, 48))
    actions = jax.random.normal(jax.random.key(2), (B, T, 7))
    mode = jnp.asarray([0, 1, 2, 0, 1, 2])
    vn, an = modes.masks(mode, jnp.asarray([0, 1, 2, 0, 2, 1]), V, K, T)
    inp = flow.noise_inputs(video, actions, jnp.ones(B, jnp.int32), vn, an, jnp.full((B,), 0.5),
                            jnp.ones_like(video), jnp.ones_like(actions))
    _, (x0_v, x0_a) = flow.predict(params, cfg, inp, (4, 4))

    def loss(tv, ta):
        return flow.masked_loss(x0_v, x0_a, tv, ta, vn[:, :, K:], an)[0]

    gv, ga = jax.grad(loss, argnums=(0, 1))(video[:, :, K:] + 1.0, actions + 1.0)
    gv_frame = np.abs(np.asarray(gv)).sum(axis=(-2, -1))  # [B, V, T]
    np.testing.assert_array_equal(gv_frame == 0, ~np.asarray(vn[:, :, K:]))
    np.testing.assert_array_equal(np.abs(np.asarray(ga)).sum(-1) == 0, ~np.asarray(an))


def test_mixed_modes_compile_once():
    cfg = ModelConfig(dim=64, depth=1, num_heads=2, num_kv_heads=1, head_dim=32, mlp_dim=64)
    params = dit.init_params(cfg, 48, jax.random.key(0))
    tok = tokenizer.PixelPatchTokenizer(4)
    traces = []

    @jax.jit
    def step(params, frames, actions, stride, rng):
        traces.append(1)
        return jax.grad(lambda p: flow.loss(p, cfg, tok.encode(frames), actions, stride, rng, (0.8, 0.1, 0.1),
                                            (4, 4))[0])(params)

    frames = jnp.zeros((8, V, K + T, 16, 16, 3), jnp.uint8)
    actions = jnp.zeros((8, T, 7))
    seen = set()
    for seed in range(6):  # different seeds -> different mode mixes in the batch
        rng = jax.random.key(seed)
        seen.add(tuple(np.asarray(modes.draw(jax.random.split(rng, 4)[0], 8, V, (0.8, 0.1, 0.1))[0])))
        step(params, frames, actions, jnp.ones(8, jnp.int32), rng)
    assert len(seen) > 1 and len(traces) == 1


def test_sampler_keeps_clean_tokens_fixed():
    cfg = ModelConfig(dim=64, depth=1, num_heads=2, num_kv_heads=1, head_dim=32, mlp_dim=64, prediction="velocity")
    params = dit.init_params(cfg, 48, jax.random.key(0))
    video = jax.random.normal(jax.random.key(1), (2, V, K + T, 16, 48))
    actions = jax.random.normal(jax.random.key(2), (2, T, 7))
    vn, an = modes.fixed(modes.CVI, 2, V, K, T, kept_view=1)
    out_v, out_a = flow.sample(params, cfg, video, actions, jnp.ones(2, jnp.int32), vn, an, jax.random.key(3), 4,
                               (4, 4))
    clean = ~np.asarray(vn)
    np.testing.assert_array_equal(np.asarray(out_v)[clean], np.asarray(video)[clean])
    np.testing.assert_array_equal(out_a, actions)
    assert not np.allclose(np.asarray(out_v)[~clean], np.asarray(video)[~clean])


def test_residual_model_starts_as_copy_last_frame():
    """Zero-initialised output + residual prediction: the untrained sampler returns the last context frame."""
    cfg = ModelConfig(dim=64, depth=1, num_heads=2, num_kv_heads=1, head_dim=32, mlp_dim=64)
    params = dit.init_params(cfg, 48, jax.random.key(0))
    video = jax.random.normal(jax.random.key(1), (2, V, K + T, 16, 48))
    vn, an = modes.fixed(modes.FD, 2, V, K, T)
    out_v, _ = flow.sample(params, cfg, video, jnp.zeros((2, T, 7)), jnp.ones(2, jnp.int32), vn, an,
                           jax.random.key(3), 5, (4, 4))
    np.testing.assert_allclose(out_v[:, :, K:], jnp.broadcast_to(video[:, :, K - 1:K], out_v[:, :, K:].shape),
                               atol=1e-5)


def test_ablation_configs_change_only_their_mode_or_horizon():
    """Each named ablation applied to a base keeps the base and changes only what the paper's ablation removes; the
    remaining modes keep the base's ratio (bussing_latent draws FD / CVI / ID 0.7 / 0.1 / 0.2)."""
    from sc3_jax.core.config import load_config

    expected = {"paper": {"ablation_no_id": (8 / 9, 1 / 9, 0.0), "ablation_no_cvi": (8 / 9, 0.0, 1 / 9)},
                "bussing_latent": {"ablation_no_id": (0.875, 0.125, 0.0), "ablation_no_cvi": (7 / 9, 0.0, 2 / 9)}}
    for base_name, by_ablation in expected.items():
        base = load_config(base_name)
        by_ablation |= {"ablation_forward_only": (1.0, 0.0, 0.0), "ablation_no_decouple": base.modes.probs}
        for name, probs in by_ablation.items():
            cfg = load_config(f"{name}:{base_name}")
            np.testing.assert_allclose(cfg.modes.probs, probs, err_msg=name)
            assert cfg.model == base.model and cfg.train == base.train, name
            horizon = base.rollout.keep_frames if name == "ablation_no_decouple" else base.data.future_frames
            assert cfg.data.future_frames == horizon, name
    with pytest.raises(ValueError, match="no training mode left"):
        modes.without((0.0, 0.0, 1.0), modes.ID)
