"""dtype policy: float32 master weights (params, grads, Adam state) with a bf16 compute dtype; bf16 params are
refused for training with a message that says what to do instead."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.model import flow
from sc3_jax.train import train
from sc3_jax.core.config import load_config, replace
from sc3_jax.model.tokenizer import make_tokenizer


def _cfg(dtype="float32", param_dtype="float32"):
    return replace(load_config("tiny"), model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16,
                                                   mlp_dim=64, rope_axes_dim=(2, 3, 3), dtype=dtype,
                                                   param_dtype=param_dtype),
                   data=dict(image_size=(16, 16), batch_size=4))


def _batch(cfg):
    rng = np.random.default_rng(0)
    return {k: (rng.integers(0, 255, s.shape) if s.dtype == jnp.uint8 else
                rng.integers(1, 3, s.shape) if s.dtype == jnp.int32 else rng.normal(size=s.shape)).astype(s.dtype)
            for k, s in train.batch_shapes(cfg).items()}


def test_bf16_compute_keeps_fp32_master_weights_and_matches_fp32_loss():
    f32, b16 = _cfg(), _cfg("bfloat16")
    batch = _batch(f32)
    state = train.init_state(f32)  # the same params for both; perturbed: zero-initialised outputs hide the dtype
    leaves, tree = jax.tree.flatten(state["params"])
    keys = jax.random.split(jax.random.key(1), len(leaves))
    state["params"] = jax.tree.unflatten(tree, [x + 0.05 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)])
    step16 = jax.jit(train.make_train_step(b16))
    new, m16 = step16(state, batch)
    # the same loss in fp32 (forward only: the noise key the train step derives from the state)
    tok = make_tokenizer(f32.model)
    rng = jax.random.fold_in(jax.random.wrap_key_data(state["rng"]), state["step"])
    loss32 = jax.jit(lambda p: flow.loss(p, f32.model, tok.encode(batch["frames"]), batch["actions"], batch["stride"],
                                         rng, f32.modes.probs, tok.grid(f32.data.image_size), f32.flow)[0])
    m32 = {"loss": loss32(state["params"])}
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(new["params"]))
    assert all(x.dtype in (jnp.float32, jnp.int32) for x in jax.tree.leaves(new["opt_state"]))
    assert abs(float(m16["loss"]) - float(m32["loss"])) < 0.02 * float(m32["loss"])
    assert float(m16["loss"]) != float(m32["loss"])  # it did compute in bf16


def test_bf16_params_are_refused_for_training():
    with pytest.raises(ValueError, match="float32 params .*master"):
        train.make_train_step(_cfg("bfloat16", "bfloat16"))
