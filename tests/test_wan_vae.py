"""Wan VAE port: shapes, tokens, gradients, checkpoint conversion; parity with diffusers under -m interop."""
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.model import wan_tokenizer as wt
from sc3_jax.model import wan_vae as wv
from sc3_jax.model import wan_vae_convert as wc
from sc3_jax.model.tokenizer import PixelPatchTokenizer

TOL = 1e-4

# Tiny architectures with the real block structure (3 spatial downsamples, 2 temporal ones).
TINY = {
    "wan2.1": {"base_dim": 8, "z_dim": 4, "dim_mult": [1, 2, 2, 2], "num_res_blocks": 1, "attn_scales": [],
               "temperal_downsample": [False, True, True]},
    "wan2.2": {"base_dim": 8, "decoder_base_dim": 16, "z_dim": 8, "dim_mult": [1, 2, 2, 2], "num_res_blocks": 1,
               "attn_scales": [], "temperal_downsample": [False, True, True], "is_residual": True,
               "in_channels": 12, "out_channels": 12, "patch_size": 2, "scale_factor_spatial": 16},
}


def _with_stats(kw, seed=0):
    rng = np.random.default_rng(seed)
    z = kw["z_dim"]
    return dict(kw, latents_mean=[float(v) for v in rng.normal(size=z)],
                latents_std=[float(v) for v in rng.uniform(0.5, 2.0, size=z)])


def _cfg(name):
    return wc.config_from_diffusers(_with_stats(TINY[name]))


# ----------------------------------------------------------------------------------------------------------------
# Without torch
# ----------------------------------------------------------------------------------------------------------------
def test_sizes_and_presets():
    c1, c2 = _cfg("wan2.1"), _cfg("wan2.2")
    assert (c1.spatial_ratio, c1.temporal_ratio, c2.spatial_ratio, c2.pixel_channels) == (8, 4, 16, 3)
    assert [c1.latent_frames(t) for t in (1, 4, 5, 7, 9)] == [1, 1, 2, 2, 3]
    assert c1.pixel_frames(3) == 9
    assert wv.wan21_config().z_dim == 16 and wv.wan21_config().latents_mean == wv.WAN21_LATENTS_MEAN
    w22 = wv.wan22_config()
    assert (w22.z_dim, w22.spatial_ratio, w22.is_residual, w22.in_channels) == (48, 16, True, 12)
    # Full-size specs build (no arrays): the Wan2.1 VAE has ~127M parameters.
    n21 = sum(int(np.prod(s.shape)) for s in wc.flat_specs(wv.wan21_config()).values())
    assert 120e6 < n21 < 135e6, n21
    with pytest.raises(ValueError, match="unknown Wan VAE"):
        wt.make_wan_tokenizer("wan3")
    with pytest.warns(UserWarning, match="randomly initialised"):
        tok = wt.make_wan_tokenizer("wan2.2", patch_size=2, base_dim=4, decoder_base_dim=4, z_dim=4,
                                    latents_mean=(0.0,) * 4, latents_std=(1.0,) * 4)
    assert tok.grid((64, 96)) == (2, 3) and tok.token_dim == 16 and tok.cfg.is_residual
    assert wt.make_wan_tokenizer("wan2.2", patch_size=2, base_dim=4, decoder_base_dim=4, z_dim=4,
                                 latents_mean=(0.0,) * 4, latents_std=(1.0,) * 4) is tok  # cached
    with pytest.raises(ValueError, match="latents_mean"):
        wv.WanVAEConfig(z_dim=4)  # default stats have 16 entries


def test_token_order_matches_pixel_tokenizer_and_pads():
    z = jax.random.normal(jax.random.key(0), (2, 3, 4, 6, 5))
    tok = wv.latents_to_tokens(z, 2)
    ref = PixelPatchTokenizer(patch_size=2, channels=5).encode(z)
    np.testing.assert_array_equal(tok, ref)
    np.testing.assert_array_equal(wv.tokens_to_latents(tok, 2, (4, 6)), z)
    zo = z[..., :3, :5, :]  # odd latent sizes: zero-padded to the patch, cropped back
    t2 = wv.latents_to_tokens(zo, 2)
    assert t2.shape == (2, 3, 2 * 3, 20)
    np.testing.assert_array_equal(wv.tokens_to_latents(t2, 2, (3, 5)), zo)


def test_patchify_inverse():
    x = jax.random.normal(jax.random.key(1), (1, 2, 8, 12, 3))
    p = wv.patchify(x, 2)
    assert p.shape == (1, 2, 4, 6, 12)
    np.testing.assert_array_equal(p[0, 0, 0, 0], jnp.stack([x[0, 0, ph, pw, c] for c in range(3) for pw in range(2)
                                                             for ph in range(2)]))
    np.testing.assert_array_equal(wv.unpatchify(p, 2), x)


def test_tokenizer_shapes_and_consistency():
    cfg = wc.config_from_diffusers(_with_stats(dict(TINY["wan2.1"], base_dim=4, dim_mult=[1, 1, 1, 1])))
    tok = wt.WanTokenizer.random(cfg, seed=0, patch_size=2)
    frames = jax.random.randint(jax.random.key(2), (1, 2, 6, 16, 32, 3), 0, 256).astype(jnp.uint8)  # 6 -> 5 used
    assert tok.grid((16, 32)) == (1, 2) and tok.token_dim == 16 and tok.latent_frames(6) == 2
    t = tok.encode(frames)
    assert t.shape == (1, 2, 2, 2, 16)
    # tokens = patchified normalised posterior mean of the video in [-1, 1]
    z, _ = wv.encode_moments_jit(tok.params, cfg, frames.reshape(2, 6, 16, 32, 3).astype(jnp.float32) / 127.5 - 1)
    ref = wv.latents_to_tokens(wv.normalize_latents(cfg, z), 2).reshape(t.shape)
    np.testing.assert_allclose(t, ref, atol=1e-5)
    x = tok.decode(t, (16, 32))
    assert x.shape == (1, 2, 5, 16, 32, 3) and float(jnp.abs(x).max()) <= 1.0
    with pytest.raises(ValueError, match="spatial ratio"):
        tok.grid((20, 32))


def test_batched_slices():
    f = jax.jit(lambda v: v * 2.0 + v.sum(axis=(1, 2), keepdims=True))  # per-item
    x = jnp.arange(5 * 2 * 3, dtype=jnp.float32).reshape(5, 2, 3)
    np.testing.assert_allclose(wv._batched(f, x, 2), f(x))
    np.testing.assert_allclose(jax.jit(lambda v: wv._batched(f, v, 2))(x), f(x))


def test_grad_of_reconstruction_loss_is_finite():
    # two levels (space 2x2 after patchify 4x, time 2x) keep the XLA:CPU compile of the backward pass short
    cfg = wc.config_from_diffusers(_with_stats(dict(TINY["wan2.2"], base_dim=4, decoder_base_dim=4, z_dim=4,
                                                    dim_mult=[1, 1], temperal_downsample=[True])))
    params = wv.init_params(cfg, jax.random.key(0))
    video = jax.random.uniform(jax.random.key(1), (1, 5, 8, 8, 3), minval=-1, maxval=1)  # 1 + 4 frames

    def loss(p):
        mean, logvar = wv.encode_moments(p, cfg, video)
        z = mean + jnp.exp(0.5 * logvar) * jax.random.normal(jax.random.key(2), mean.shape)
        rec = wv.decode(p, cfg, z, clamp=False)
        assert mean.shape == (1, 3, 2, 2, 4) and rec.shape == video.shape
        return jnp.mean((rec - video) ** 2) + 1e-6 * jnp.mean(wv.kl_divergence(mean, logvar))

    val, g = jax.jit(jax.value_and_grad(loss))(params)
    leaves = jax.tree.leaves(g)
    assert np.isfinite(float(val)) and all(bool(jnp.all(jnp.isfinite(x))) for x in leaves)
    assert float(jnp.abs(g["encoder"]["conv_in"]["weight"]).sum()) > 0  # reaches the first layer
    assert float(jnp.abs(g["decoder"]["conv_out"]["weight"]).sum()) > 0


def test_state_dict_roundtrip_and_key_errors():
    for name in TINY:
        cfg = _cfg(name)
        params = wv.init_params(cfg, jax.random.key(3))
        sd = wc.state_dict_from_params(cfg, params)
        assert sd["encoder.conv_in.weight"].shape == (cfg.base_dim, cfg.in_channels, 3, 3, 3)
        back = wc.params_from_state_dict(cfg, sd)
        jax.tree.map(np.testing.assert_array_equal, back, params)
        assert wc.config_from_diffusers(wc.config_to_diffusers(cfg)) == cfg
    bad = dict(sd)
    del bad["decoder.conv_out.bias"]
    bad["decoder.extra.weight"] = np.zeros(3, np.float32)
    bad["encoder.conv_in.weight"] = bad["encoder.conv_in.weight"][:1]
    with pytest.raises(ValueError) as e:
        wc.params_from_state_dict(cfg, bad)
    msg = str(e.value)
    assert "decoder.conv_out.bias" in msg and "decoder.extra.weight" in msg and "encoder.conv_in.weight" in msg
    with pytest.raises(ValueError, match="unknown AutoencoderKLWan config keys"):
        wc.config_from_diffusers(dict(wc.config_to_diffusers(cfg), fancy_option=1))


def test_save_and_load_files(tmp_path):
    pytest.importorskip("safetensors")
    for name in TINY:
        cfg = _cfg(name)
        params = wv.init_params(cfg, jax.random.key(4))
        wc.save_diffusers(cfg, params, str(tmp_path / name))
        cfg2, p2 = wc.load_diffusers(str(tmp_path / name))
        assert cfg2 == cfg
        jax.tree.map(np.testing.assert_array_equal, p2, params)
        # the header-parsing reader (used for bfloat16 files) agrees with safetensors.numpy
        f = str(tmp_path / name / wc.WEIGHTS_NAME)
        raw, ref = wc._read_safetensors_raw(f), wc.read_safetensors(f)
        assert raw.keys() == ref.keys() and all(np.array_equal(raw[k], ref[k]) for k in ref)


# ----------------------------------------------------------------------------------------------------------------
# Parity with diffusers (extra [interop])
# ----------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module", params=list(TINY))
def diffusers_vae(request, tmp_path_factory):
    torch = pytest.importorskip("torch")
    diffusers = pytest.importorskip("diffusers")
    torch.manual_seed(0)
    model = diffusers.AutoencoderKLWan(**_with_stats(TINY[request.param])).eval()
    path = str(tmp_path_factory.mktemp(request.param.replace(".", "")))
    model.save_pretrained(path)
    return request.param, model, path


def _ncthw(x):  # ours [B, T, H, W, C] -> torch layout
    return np.asarray(x).transpose(0, 4, 1, 2, 3)


@pytest.mark.interop
def test_parity_with_diffusers(diffusers_vae):
    import torch
    name, model, path = diffusers_vae
    tok = wt.WanTokenizer.from_pretrained(path)
    cfg, params = tok.cfg, tok.params
    assert cfg.is_residual == (name == "wan2.2")
    gen = torch.Generator().manual_seed(1)
    frames = torch.randint(0, 256, (1, 9, 32, 48, 3), generator=gen, dtype=torch.uint8)  # 1 + 4 + 4 frames
    video = frames.permute(0, 4, 1, 2, 3).float() / 127.5 - 1.0
    with torch.no_grad():
        post = model.encode(video).latent_dist
        mu, logvar = post.mode(), post.logvar
        rec = model.decode(mu).sample
    mean_ref = (mu - torch.tensor(cfg.latents_mean).view(1, -1, 1, 1, 1)) * (
        1.0 / torch.tensor(cfg.latents_std).view(1, -1, 1, 1, 1))

    mean, lv = wv.encode_moments_jit(params, cfg, jnp.asarray(video.permute(0, 2, 3, 4, 1)))
    assert mean.shape[1] == 3
    err_mu = np.abs(_ncthw(mean) - mu.numpy()).max()
    err_lv = np.abs(_ncthw(lv) - logvar.numpy()).max()
    out = wv.decode_jit(params, cfg, jnp.asarray(mu.permute(0, 2, 3, 4, 1)), True)
    err_dec = np.abs(_ncthw(out) - rec.numpy()).max()
    # the tokenizer (uint8 -> normalised latent tokens and back) against the pipelines' normalisation
    tokens = tok.encode(jnp.asarray(frames.numpy()))
    z_tok = wv.tokens_to_latents(tokens, 1, tok.latent_size((32, 48)))
    err_tok = np.abs(_ncthw(z_tok) - mean_ref.numpy()).max()
    rec_tok = tok.decode(wv.latents_to_tokens(jnp.asarray(mean_ref.permute(0, 2, 3, 4, 1)), 1), (32, 48))
    err_tok = max(err_tok, np.abs(_ncthw(rec_tok) - rec.numpy()).max())
    print(f"\n{name}: max abs error encode mean {err_mu:.2e}, logvar {err_lv:.2e}, decode {err_dec:.2e}, "
          f"tokens {err_tok:.2e}")
    assert (np.abs(rec.numpy()) < 0.999).mean() > 0.9  # the decode comparison is not of saturated pixels
    assert max(err_mu, err_lv, err_dec, err_tok) <= TOL


@pytest.mark.interop
def test_checkpoint_roundtrip_is_identical(diffusers_vae, tmp_path):
    import torch
    from diffusers import AutoencoderKLWan
    from safetensors.numpy import load_file
    name, model, path = diffusers_vae
    cfg, params = wc.load_diffusers(path)
    out = wc.save_diffusers(cfg, params, str(tmp_path / "ours"))
    a, b = load_file(os.path.join(path, wc.WEIGHTS_NAME)), load_file(os.path.join(out, wc.WEIGHTS_NAME))
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape and np.array_equal(a[k], b[k]), k
    reloaded = AutoencoderKLWan.from_pretrained(out).eval()
    sd0, sd1 = model.state_dict(), reloaded.state_dict()
    assert sd0.keys() == sd1.keys() and all(torch.equal(sd0[k], sd1[k]) for k in sd0)
    with open(os.path.join(path, "config.json")) as f:
        orig = json.load(f)
    assert all(reloaded.config[k] == v for k, v in orig.items() if not k.startswith("_"))
    tok = wt.make_wan_tokenizer(name, path)
    assert tok.cfg == cfg and tok.token_dim == cfg.z_dim
    with pytest.raises(ValueError, match="style VAE"):
        wt.make_wan_tokenizer("wan2.1" if name == "wan2.2" else "wan2.2", path)


@pytest.mark.interop
def test_reads_bfloat16_checkpoints(tmp_path):
    torch = pytest.importorskip("torch")
    st = pytest.importorskip("safetensors.torch")
    t = torch.randn(4, 3).to(torch.bfloat16)
    st.save_file({"w": t}, str(tmp_path / "x.safetensors"))
    got = wc.read_safetensors(str(tmp_path / "x.safetensors"))["w"]
    np.testing.assert_array_equal(got.astype(np.float32), t.float().numpy())
