"""The learned latent tokenizer: autoencoder shapes and files, the tokenizer interface, its trainer (learning,
exact resume, export) and the latent cache the training pipeline reads."""
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.train import tokenizer_train as tt
from sc3_jax.core.config import DataConfig, ModelConfig
from sc3_jax.data import latent_cache, norm_stats, pipeline
from sc3_jax.data import synthetic as S
from sc3_jax.model import autoencoder as ae
from sc3_jax.model.tokenizer import ConvAETokenizer, make_tokenizer

SMALL = ae.AEConfig(latent_channels=4, width=16, mid_width=8, out_width=8, blocks=1)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("episodes")
    return S.generate(root, num_episodes=3, length=12, image_size=(16, 16), seed=2, progress=False)


@pytest.fixture(scope="module")
def trained(store, tmp_path_factory):
    """A few trainer steps on the synthetic store (exported to workdir/tokenizer)."""
    work = tmp_path_factory.mktemp("tok")
    cfg = tt.TokenizerTrainConfig(data=str(store.root), heldout=str(store.root), workdir=str(work), steps=30,
                                  batch_size=8, lr=3e-3, warmup_steps=5, ckpt_every=10, eval_frames=8,
                                  progress=False)
    result = tt.train(cfg, SMALL)
    return cfg, work, result


@pytest.mark.parametrize("downsample", [2, 4, 8])
def test_shapes_and_standardisation(downsample):
    cfg = ae.AEConfig(latent_channels=3, downsample=downsample, width=8, mid_width=8, out_width=4)
    p = ae.init(cfg, jax.random.key(0))
    x = jax.random.randint(jax.random.key(1), (2, 5, 32, 32, 3), 0, 256).astype(jnp.uint8)
    stats = {"mean": jnp.arange(3.0), "std": jnp.full((3,), 2.0)}
    z = ae.encode(p, stats, x)
    assert z.shape == (2, 5, 32 // downsample, 32 // downsample, 3)
    raw = ae.encode_raw(p, x.reshape(-1, 32, 32, 3).astype(jnp.float32) / 127.5 - 1)
    np.testing.assert_allclose(z.reshape(raw.shape), (raw - stats["mean"]) / 2.0, rtol=1e-5, atol=1e-5)
    y = ae.decode(p, stats, z)
    assert y.shape == x.shape and float(jnp.abs(y).max()) <= 1.0
    with pytest.raises(ValueError, match="power of two"):
        ae.AEConfig(downsample=3)


def test_space_to_depth_round_trip():
    x = jax.random.normal(jax.random.key(0), (2, 8, 12, 3))
    s = ae.space_to_depth(x, 2)
    assert s.shape == (2, 4, 6, 12)
    np.testing.assert_array_equal(ae.depth_to_space(s, 2), x)
    np.testing.assert_array_equal(s[0, 1, 2, :3], x[0, 2, 4])  # block (1, 2) starts at pixel (2, 4)


def test_save_load_round_trip_and_bad_files(tmp_path):
    p = ae.init(SMALL, jax.random.key(3))
    stats = {"mean": np.linspace(0, 1, 4), "std": np.linspace(1, 2, 4)}
    ae.save(tmp_path / "t", SMALL, (16, 16), p, stats)
    cfg, size, p2, st2 = ae.load(tmp_path / "t")
    assert cfg == SMALL and size == (16, 16)
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), p, p2))
    np.testing.assert_allclose(st2["std"], stats["std"], rtol=1e-6)
    with pytest.raises(FileNotFoundError, match="train-tokenizer"):
        ae.load(tmp_path / "missing")
    meta = json.loads((tmp_path / "t" / "ae.json").read_text())
    meta["config"]["width"] = 32
    (tmp_path / "t" / "ae.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="shape"):
        ae.load(tmp_path / "t")


def test_trainer_learns_and_exports(trained, store):
    cfg, work, result = trained
    rows = [json.loads(line) for line in (work / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 30 and rows[-1]["loss"] < rows[0]["loss"]
    assert set(result["heldout"]) == {"left", "right", "wrist"}
    for v in result["heldout"].values():
        assert np.isfinite(v["psnr"]) and 0 <= v["moving_fraction"] <= 1
    tok = make_tokenizer(ModelConfig(tokenizer="conv_ae", tokenizer_path=str(work / "tokenizer"), patch_size=2))
    assert isinstance(tok, ConvAETokenizer) and tok.grid((16, 16)) == (2, 2) and tok.token_dim == 2 * 2 * 4
    frames = store.load(store.episode_ids()[0]).frames["left"][:3]
    tokens = tok.encode(frames)
    assert tokens.shape == (3, 4, 16)
    np.testing.assert_array_equal(tokens, tok.from_latents(tok.encode_latents(frames)))
    assert tok.decode(tokens, (16, 16)).shape == (3, 16, 16, 3)
    with pytest.raises(ValueError, match="trained on"):
        tok.grid((32, 32))


def test_trainer_resume_is_exact(trained, tmp_path):
    """Stopped after 20 steps and resumed (as a new process would) == 30 uninterrupted steps, bit for bit."""
    import dataclasses
    cfg, work, _ = trained
    cfg = dataclasses.replace(cfg, workdir=str(tmp_path), heldout=None)
    tt.train(cfg, SMALL, stop_at=20)
    assert (tmp_path / "checkpoints" / "20").exists()
    tt.train(cfg, SMALL)
    _, _, a, _ = ae.load(tmp_path / "tokenizer")
    _, _, b, _ = ae.load(work / "tokenizer")
    assert all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
    with pytest.raises(ValueError, match="architecture"):
        tt.train(cfg, dataclasses.replace(SMALL, width=24))


def test_latent_cache_matches_encoder_and_refuses_other_tokenizer(trained, store, tmp_path):
    _, work, _ = trained
    tok = ConvAETokenizer(str(work / "tokenizer"), 2)
    views = ("left", "right", "wrist")
    root = latent_cache.build(store, tok, views, tmp_path / "lat", batch=16, progress=False)
    ids = store.episode_ids()
    reader = latent_cache.LatentReader(root, ids)
    ep = store.load(ids[1])
    idx = np.array([0, 3, 7])
    got = reader.window(1, idx)
    want = np.stack([np.asarray(tok.encode_latents(ep.frames[v][idx])) for v in views])
    assert got.dtype == np.float16 and got.shape == want.shape
    np.testing.assert_allclose(got, want, atol=2e-2, rtol=2e-3)  # float16 storage
    # the pipeline serves cached latents instead of frames
    cfg = DataConfig(path=str(store.root), image_size=(16, 16), batch_size=4, context_frames=2, future_frames=3)
    stats = norm_stats.NormStats.from_store(store)
    index = pipeline.build_index(store, cfg)
    b = pipeline.make_dataset(cfg, store, stats, index=index, latents=latent_cache.LatentReader(root, index.episode_ids))[0]
    assert "frames" not in b and b["latents"].shape == (4, 3, 5, 4, 4, 4)
    # ... with the same windows as the frame path (its actions / poses come from the trajectory-only reader)
    f = pipeline.make_dataset(cfg, store, stats, index=index)[0]
    for k in ("actions", "pose", "episode", "start", "stride", "pseudo"):
        np.testing.assert_array_equal(b[k], f[k], err_msg=k)
    # another tokenizer's weights: refused
    p = ae.init(SMALL, jax.random.key(9))
    ae.save(tmp_path / "other", SMALL, (16, 16), p, {"mean": np.zeros(4), "std": np.ones(4)})
    with pytest.raises(ValueError, match="another tokenizer"):
        latent_cache.build(store, ConvAETokenizer(str(tmp_path / "other"), 2), views, root, progress=False)
    with pytest.raises(FileNotFoundError, match="no cached latents"):
        latent_cache.LatentReader(tmp_path / "empty", ids)


def test_exported_world_model_carries_its_tokenizer(trained, tmp_path):
    """An exported conv_ae world model holds its tokenizer and finds it wherever the directory is moved."""
    import shutil

    from sc3_jax.model import checkpoint
    from sc3_jax.train import train
    from sc3_jax.core.config import Config

    _, work, _ = trained
    cfg = Config(model=ModelConfig(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64,
                                   rope_axes_dim=(4, 2, 2), tokenizer="conv_ae",
                                   tokenizer_path=str(work / "tokenizer"), patch_size=2),
                 data=DataConfig(image_size=(16, 16)))
    params = train.init_state(cfg)["params"]
    stats = norm_stats.NormStats(np.zeros(7), np.ones(7))
    checkpoint.save(tmp_path / "wm", cfg, stats, params)
    assert json.loads((tmp_path / "wm" / "config.json").read_text())["model"]["tokenizer_path"] == "tokenizer"
    shutil.move(tmp_path / "wm", tmp_path / "moved")
    cfg2, _, params2 = checkpoint.load(tmp_path / "moved")
    assert cfg2.model.tokenizer_path == str((tmp_path / "moved" / "tokenizer").absolute())
    assert make_tokenizer(cfg2.model).token_dim == 2 * 2 * 4
    assert jax.tree.structure(params2) == jax.tree.structure(params)


def test_tokenizer_first_built_inside_a_trace(trained):
    """make_tokenizer caches the loaded weights; built first under a jit trace (as checkpoint.load_params does through
    eval_shape), they must still be concrete arrays when used afterwards."""
    from sc3_jax.model import tokenizer as T

    _, work, _ = trained
    mcfg = ModelConfig(tokenizer="conv_ae", tokenizer_path=str(work / "tokenizer"), patch_size=2)
    T._conv_ae.cache_clear()
    jax.eval_shape(lambda: make_tokenizer(mcfg).encode(jnp.zeros((1, 16, 16, 3), jnp.uint8)))
    out = make_tokenizer(mcfg).encode(np.zeros((1, 16, 16, 3), np.uint8))  # UnexpectedTracerError before the fix
    assert out.shape == (1, 4, 16) and bool(jnp.all(jnp.isfinite(out)))


def test_the_tokenizer_trains_on_every_view_of_its_data_unless_told(tmp_path):
    """No robot's cameras are a default: a one-camera store (an SO-101's `front`) is sampled as it is."""
    from sc3_jax.data.action_space import ActionSpace
    from sc3_jax.data.episodes import Episode, EpisodeStore
    from sc3_jax.core.errors import UserError
    from sc3_jax.core.tokenizer_config import TokenizerTrainConfig
    from sc3_jax.train.tokenizer_train import ImageSampler

    st = EpisodeStore(tmp_path / "s", views=["front"], fps=10, image_size=(8, 8), create=True,
                      action_space=ActionSpace("absolute", 2), has_pose=False)
    st.write(Episode("e0", {"front": np.zeros((3, 8, 8, 3), np.uint8)}, np.zeros((3, 2), np.float32), None))
    assert TokenizerTrainConfig().views is None
    assert ImageSampler(str(st.root), None).views == ("front",)
    with pytest.raises(UserError, match="lack \\['wrist'\\]"):
        ImageSampler(str(st.root), ("front", "wrist"))
