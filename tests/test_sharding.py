"""One train step on several meshes of 8 forced CPU devices gives the same loss and params as on one device."""
import jax
import numpy as np
import pytest

from sc3_jax.model import sharding
from sc3_jax.train import train
from sc3_jax.core.config import Config, DataConfig, MeshConfig, ModelConfig, TrainConfig


def small_config(mesh=(1, 1, 1)) -> Config:
    return Config(model=ModelConfig(dim=64, depth=2, num_heads=4, num_kv_heads=2, head_dim=32, mlp_dim=128),
                  data=DataConfig(image_size=(8, 8), context_frames=1, future_frames=2, batch_size=8),
                  train=TrainConfig(lr=1e-3, warmup_steps=1, steps=10),
                  mesh=MeshConfig(*mesh))


def random_batch(cfg: Config) -> dict:
    rng = np.random.default_rng(0)
    shapes = train.batch_shapes(cfg)
    return {"frames": rng.integers(0, 256, shapes["frames"].shape, dtype=np.uint8),
            "actions": rng.normal(size=shapes["actions"].shape).astype(np.float32),
            "stride": rng.integers(1, 3, shapes["stride"].shape).astype(np.int32)}


def one_step(cfg: Config, devices):
    mesh = sharding.make_mesh(cfg.mesh, devices)
    step, _ = train.compile_train_step(cfg, mesh)
    state = train.create_state(cfg, mesh)
    state, metrics = step(state, sharding.global_batch(mesh, random_batch(cfg)))
    return float(metrics["loss"]), jax.device_get(state["params"]), state


@pytest.fixture(scope="module")
def reference():
    return one_step(small_config(), jax.devices()[:1])


@pytest.mark.parametrize("mesh", [(8, 1, 1), (2, 2, 2), (1, 4, 2)])
def test_sharded_step_matches_single_device(reference, mesh):
    assert len(jax.devices()) == 8
    loss, params, state = one_step(small_config(mesh), jax.devices())
    ref_loss, ref_params, _ = reference
    assert loss == pytest.approx(ref_loss, rel=1e-5)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(ref_params)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    # the state really is distributed as the rules say
    wq = state["params"]["layers"]["wq"]
    assert wq.sharding.shard_shape(wq.shape) == (2, 64 // mesh[1], 4 // mesh[2], 32)


def test_mesh_shape_errors():
    assert sharding.mesh_shape(MeshConfig(-1, 2, 2), 8) == (2, 2, 2)
    with pytest.raises(ValueError, match="needs 6 devices"):
        sharding.mesh_shape(MeshConfig(3, 2, 1), 8)
    with pytest.raises(ValueError, match="at most one"):
        sharding.mesh_shape(MeshConfig(-1, -1, 1), 8)


@pytest.mark.slow  # 25-55 s: kept out of the default run's 15 minutes (CI runs -m slow too)
def test_gradient_accumulation_is_the_mean_of_micro_batch_gradients():
    """grad_accum = 2 on a 4-device data mesh: the update equals one computed by hand from the two micro-batches
    (samples 0, 2, 4, .. and 1, 3, 5, ..; noise keys fold_in(step key, i)) with the mean of their gradients."""
    import optax

    from sc3_jax.model import flow
    from sc3_jax.core.config import replace
    from sc3_jax.model.tokenizer import make_tokenizer

    cfg = replace(small_config((4, 1, 1)), train=dict(grad_accum=2))
    batch = random_batch(cfg)
    _, params, state = one_step(cfg, jax.devices()[:4])
    init = jax.device_get(train.init_state(cfg))
    rng = jax.random.fold_in(jax.random.wrap_key_data(init["rng"]), 0)
    tok = make_tokenizer(cfg.model)

    @jax.jit  # one compile for both micro-batches (eager op-by-op backward took minutes)
    def grads(params, mb, key):
        loss = lambda p: flow.loss(p, cfg.model, tok.encode(mb["frames"]), mb["actions"], mb["stride"],  # noqa
                                   key, cfg.modes.probs, (2, 2), cfg.flow)[0]
        return jax.grad(loss)(params)

    g0, g1 = (grads(init["params"], {k: v[i::2] for k, v in batch.items()}, jax.random.fold_in(rng, i))
              for i in range(2))
    g = jax.tree.map(lambda a, b: (a + b) / 2, g0, g1)
    opt = train.make_optimizer(cfg)
    updates, _ = opt.update(g, init["opt_state"], init["params"])
    expected = optax.apply_updates(init["params"], updates)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="grad_accum = 3"):
        train.make_train_step(replace(cfg, train=dict(grad_accum=3)))
