"""``train.init_from``: a run starts from another run's (or an exported model's) params with a fresh optimizer and
the source's action normalisation; a shape mismatch is refused with every offending leaf named."""
import dataclasses
import json

import jax
import numpy as np
import pytest

from sc3_jax.model import checkpoint, sharding
from sc3_jax.train import train
from sc3_jax.core.config import Config, DataConfig, ModelConfig, TrainConfig, replace
from sc3_jax.data import synthetic
from sc3_jax.data.norm_stats import NormStats


def _cfg(data, workdir, **model) -> Config:
    m = dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64, rope_axes_dim=(2, 3, 3))
    return Config(model=ModelConfig(**{**m, **model}),
                  data=DataConfig(path=str(data), image_size=(8, 8), context_frames=1, future_frames=2, batch_size=8),
                  train=TrainConfig(workdir=str(workdir), steps=3, ckpt_every=3, log_every=1, lr=1e-3, warmup_steps=1,
                                    progress=False, tensorboard=False, async_checkpointing=False))


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("init_from")
    data = tmp / "episodes"
    synthetic.generate(str(data), 4, length=20, image_size=(8, 8), seed=0, progress=False)
    cfg = _cfg(data, tmp / "src")
    train.train(cfg)
    return tmp, data, cfg


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree.leaves(jax.device_get(tree))]


@pytest.mark.parametrize("kind", ["workdir", "exported"])
def test_init_from_loads_params_fresh_optimizer_and_source_stats(source, kind):
    tmp, data, src_cfg = source
    src = tmp / "src"
    _, stats, params = checkpoint.load(src)
    if kind == "exported":
        # a different norm-stats file in the exported dir proves the fine-tune reads the *source's* stats
        stats = dataclasses.replace(stats, **{k: np.asarray(getattr(stats, k)) * 2
                                              for k in ("mean", "std", "pose_mean", "pose_std")})
        src = checkpoint.save(tmp / "exported", src_cfg, stats, jax.device_get(params), np.float32)
    cfg = replace(_cfg(data, tmp / f"ft_{kind}"), train=dict(init_from=str(src)))
    state = train.create_state(cfg, sharding.make_mesh(cfg.mesh))  # all 8 host devices: placed sharded
    assert int(state["step"]) == 0
    for a, b in zip(_leaves(state["params"]), _leaves(params)):
        np.testing.assert_array_equal(a, b)
    # Adam moments start at zero, not at the source's
    mu = [x for x in _leaves(state["opt_state"]) if x.ndim > 0]
    assert mu and all(not np.any(x) for x in mu)
    train.prepare_data(cfg)
    assert json.loads((tmp / f"ft_{kind}" / "norm_stats.json").read_text()) == \
        json.loads((src / "norm_stats.json").read_text())


def test_init_from_refuses_other_shapes_naming_the_leaves(source):
    tmp, data, _ = source
    cfg = _cfg(data, tmp / "bad", dim=48, mlp_dim=96)
    cfg = replace(cfg, train=dict(init_from=str(tmp / "src")))
    with pytest.raises(ValueError, match=r"do not fit this model config:\n  wrong shape \(\d+\):\n.*\(expected"):
        train.create_state(cfg, sharding.make_mesh(cfg.mesh))


def test_init_from_missing_dir_is_a_clear_error(tmp_path):
    cfg = _cfg(tmp_path, tmp_path / "x")
    cfg = replace(cfg, train=dict(init_from=str(tmp_path / "nowhere")))
    with pytest.raises(FileNotFoundError, match="init_from .*no config.json"):
        train.create_state(cfg, sharding.make_mesh(cfg.mesh))


@pytest.mark.parametrize("kind", ["workdir", "exported"])
def test_init_from_reads_params_straight_into_their_shards(source, kind):
    """With an FSDP mesh over the 8 host devices, every leaf arrives with the train state's sharding (big leaves
    split, not a full copy per device) and the source's values; the optimizer state of a workdir is not read."""
    tmp, data, src_cfg = source
    src = tmp / "src"
    _, _, params = checkpoint.load(src)
    if kind == "exported":
        src = checkpoint.save(tmp / "exported_fsdp", src_cfg, checkpoint.load(src)[1],
                                     jax.device_get(params), np.float16)
    cfg = replace(_cfg(data, tmp / f"fsdp_{kind}"), train=dict(init_from=str(src)), mesh=dict(data=1, fsdp=-1))
    mesh = sharding.make_mesh(cfg.mesh)
    _, st_shard = train.state_shardings(cfg, mesh)
    got = checkpoint.load_init_from(cfg, st_shard["params"])
    flat_got, flat_want = jax.tree.leaves(got), jax.tree.leaves(st_shard["params"])
    assert all(g.sharding == w for g, w in zip(flat_got, flat_want))
    split = [g for g in flat_got if not g.sharding.is_fully_replicated]
    assert split and all(g.addressable_shards[0].data.size * 8 == g.size for g in split)
    tol = 1e-3 if kind == "exported" else 0  # float16 storage
    for a, b in zip(_leaves(got), _leaves(params)):
        np.testing.assert_allclose(a, b, atol=tol * np.abs(b).max(), rtol=tol)
    assert checkpoint.source_shapes(src) == {jax.tree_util.keystr(k): v.shape
                                        for k, v in jax.tree_util.tree_flatten_with_path(params)[0]}
