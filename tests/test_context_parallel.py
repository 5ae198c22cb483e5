"""Context-parallel attention (sequence split over a "context" mesh axis of 8 CPU devices) equals dense attention,
forward and gradient, with and without masks; the DiT and a whole train step give the same numbers with it."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import NamedSharding, PartitionSpec as P

from sc3_jax.model import flow, modes, sharding
from sc3_jax.train import train
from sc3_jax.core.config import MeshConfig, ModelConfig, replace
from sc3_jax.model import context_parallel as cp
from sc3_jax.model import attention, dit, layers, tokenizer

MESHES = {"data2_ctx4": MeshConfig(data=2, fsdp=1, tensor=1, context=4),
          "tensor2_ctx4": MeshConfig(data=1, fsdp=1, tensor=2, context=4)}


def replace_impl(cfg, impl):
    return dataclasses.replace(cfg, attention_impl=impl)


def _qkv(B, N, M, hq=4, hkv=2, d=8):
    ks = jax.random.split(jax.random.key(0), 4)
    return (jax.random.normal(ks[0], (B, N, hq, d)), jax.random.normal(ks[1], (B, M, hkv, d)),
            jax.random.normal(ks[2], (B, M, hkv, d)), jax.random.normal(ks[3], (B, N, hq, d)))


def _mask(kind, B, N, M):
    if kind is None:
        return None
    if kind == "causal":  # dit's causal context attention: context prefix, then a random mix of clean/noisy tokens
        noisy = jax.random.bernoulli(jax.random.key(5), 0.5, (B, M))
        seg = attention.causal_segments(noisy, M // 4)
        return attention.SegmentMask(seg[:, M - N:], seg, attention.CAUSAL_TABLE)
    # an arbitrary 3-segment table, including a query segment that sees nothing (fully masked rows)
    table = ((True, False, True), (False, True, False), (False, False, False))
    return attention.SegmentMask(jax.random.randint(jax.random.key(6), (B, N), 0, 3),
                          jax.random.randint(jax.random.key(7), (B, M), 0, 3), table)


def _out_and_grads(fn, q, k, v, ct):
    """(output, d sum(output * ct) / d(q, k, v)) in one program."""
    def f(q, k, v):
        out = fn(q, k, v)
        return jnp.sum(out * ct), out
    (_, out), grads = jax.jit(jax.value_and_grad(f, argnums=(0, 1, 2), has_aux=True))(q, k, v)
    return out, grads


CASES = [("data2_ctx4", ring, mask) for ring in (False, True) for mask in (None, "causal")] + \
        [("tensor2_ctx4", ring, "table") for ring in (False, True)]


@pytest.mark.parametrize("mesh_name,ring,mask_kind", CASES)
def test_attention_matches_dense(mesh_name, ring, mask_kind):
    # tensor2_ctx4: heads split over "tensor" too, sequence lengths that do not divide by 4 (padded inside), an
    # arbitrary segment table with fully masked rows
    B, N, M = (2, 24, 32) if mesh_name == "data2_ctx4" else (1, 22, 30)
    q, k, v, ct = _qkv(B, N, M)
    mask = _mask(mask_kind, B, N, M)
    dense_mask = None if mask is None else mask.dense()
    ref_out, ref_grads = _out_and_grads(lambda q, k, v: layers.attention(q, k, v, dense_mask), q, k, v, ct)
    mesh = sharding.make_mesh(MESHES[mesh_name])
    with jax.set_mesh(mesh):
        out, grads = _out_and_grads(lambda q, k, v: cp.attention(q, k, v, mask, ring=ring), q, k, v, ct)
    np.testing.assert_allclose(out, ref_out, atol=1e-5, rtol=1e-5)
    for g, r in zip(grads, ref_grads):
        np.testing.assert_allclose(g, r, atol=1e-5, rtol=1e-5)


def test_segment_mask_is_dit_causal_mask():
    cfg = ModelConfig(context_attention="causal")
    noisy = jax.random.bernoulli(jax.random.key(0), 0.5, (3, 20))
    for q_start in (0, 8):
        dense = dit._attention_mask(cfg, noisy, 8, q_start)
        seg = dit._attention_mask(replace_impl(cfg, "ring"), noisy, 8, q_start)
        assert np.array_equal(seg.dense(), dense)


def test_no_context_axis_falls_back_to_blockwise():
    q, k, v, _ = _qkv(2, 12, 12)
    mask = _mask("causal", 2, 12, 12)
    ref = jax.jit(lambda q, k, v: layers.attention(q, k, v, mask.dense()))(q, k, v)
    fn = jax.jit(lambda q, k, v: cp.attention(q, k, v, mask, ring=True))
    np.testing.assert_allclose(fn(q, k, v), ref, atol=1e-6, rtol=1e-6)  # no mesh set: the blockwise kernel
    with jax.set_mesh(sharding.make_mesh(MeshConfig(data=8))):  # a mesh without a context axis
        np.testing.assert_allclose(fn(q, k, v), ref, atol=1e-6, rtol=1e-6)


# ----------------------------------------------------------------------------------------------------------------
# The model and the train step
# ----------------------------------------------------------------------------------------------------------------
H, V, K, T = 16, 1, 2, 4  # 16 tokens per frame: 1 view x 6 frames x 16 + 4 actions = 100 tokens (100 % 4 == 0)


def _model(impl, context_attention):
    cfg = ModelConfig(dim=32, depth=2, num_heads=4, num_kv_heads=2, head_dim=16, mlp_dim=64, rope_axes_dim=(4, 2, 2),
                      num_views=V, view_embedding=True, prediction="velocity", context_attention=context_attention,
                      attention_impl=impl)
    tok = tokenizer.PixelPatchTokenizer(4)
    shapes = jax.eval_shape(lambda: dit.init_params(cfg, tok.token_dim, jax.random.key(0), tok.grid((H, H))))
    rng = np.random.default_rng(0)  # random everything (also the zero-initialised weights): outputs see all params
    params = jax.tree.map(lambda x: (rng.normal(size=x.shape) / np.sqrt(x.shape[-1])).astype(np.float32), shapes)
    return cfg, tok, params


def _inputs(tok, mode):
    rng = np.random.default_rng(1)
    video = tok.encode(rng.integers(0, 256, (2, V, K + T, H, H, 3)).astype(np.uint8))
    actions = rng.normal(size=(2, T, 7)).astype(np.float32)
    vn, an = modes.fixed(mode, 2, V, K, T)
    return flow.noise_inputs(video, actions, jnp.asarray([1, 2]), vn, an, jnp.asarray([0.3, 0.8]),
                             rng.normal(size=video.shape).astype(np.float32),
                             rng.normal(size=actions.shape).astype(np.float32))


def test_dit_apply_matches_dense():
    """dit.apply under jit on a mesh with context=4: both impls equal the dense model; the rollout's cached path
    (context keys/values computed once, then only the later tokens as queries) too. (Gradients through the whole
    model: the train-step test below.)"""
    cfg, tok, params = _model("dense", "causal")
    grid = tok.grid((H, H))
    inp = _inputs(tok, modes.FD)
    ref = jax.jit(lambda p, i: dit.apply(p, cfg, i, grid))(params, inp)
    cfg_ag, cfg_ring = replace_impl(cfg, "context_parallel"), replace_impl(cfg, "ring")

    def outputs(p, i):  # one program: both impls, and the ring impl's cached path
        kv = dit.encode_context(p, cfg_ring, i, grid)
        return dit.apply(p, cfg_ag, i, grid), dit.apply(p, cfg_ring, i, grid), dit.apply_cached(p, cfg_ring, i,
                                                                                                 grid, kv)

    mesh = sharding.make_mesh(MeshConfig(data=2, context=4))
    with jax.set_mesh(mesh):
        outs = jax.jit(outputs)(params, jax.device_put(inp, NamedSharding(mesh, P("data"))))
    for out, atol in zip(outs, (1e-5, 1e-5, 2e-5)):  # (video, action) outputs; the cached path sums differently
        for a, b in zip(out, ref):
            np.testing.assert_allclose(a, b, atol=atol, rtol=1e-5)


def test_param_tree_unchanged_by_attention_impl():
    def shapes_of(impl):
        return jax.eval_shape(lambda: dit.init_params(ModelConfig(attention_impl=impl), 48, jax.random.key(0), (4, 4)))

    shapes = {impl: shapes_of(impl) for impl in ("dense", "ring")}
    assert jax.tree.structure(shapes["dense"]) == jax.tree.structure(shapes["ring"])
    assert jax.tree.leaves(shapes["dense"]) == jax.tree.leaves(shapes["ring"])


def test_train_step_with_context_mesh_matches_single_device():
    """A whole train step (loss, gradients, AdamW) with ring attention on a (data=4, context=2) mesh equals the dense
    model on one device: the train.compile_train_step change proposed in the report is ``sharding.bind_mesh``."""
    from test_sharding import random_batch, small_config

    cfg = replace(small_config(), model=dict(attention_impl="ring", context_attention="causal", dim=32, depth=1,
                                             mlp_dim=64),
                  mesh=MeshConfig(data=4, fsdp=1, tensor=1, context=2))
    results = []
    for c, devices in ((replace(cfg, model=dict(attention_impl="dense"), mesh=MeshConfig(1, 1, 1)),
                        jax.devices()[:1]), (cfg, jax.devices())):
        mesh = sharding.make_mesh(c.mesh, devices)
        step, _ = train.compile_train_step(c, mesh)
        step = sharding.bind_mesh(step, mesh)  # the one-line change proposed for train.compile_train_step
        state = train.create_state(c, mesh)
        state, metrics = step(state, sharding.global_batch(mesh, random_batch(c)))
        results.append((jax.device_get(metrics), jax.device_get(state["params"])))
    assert dict(mesh.shape) == {"data": 4, "fsdp": 1, "tensor": 1, "context": 2}
    (ref_m, ref_p), (m, p) = results
    assert float(m["loss"]) == pytest.approx(float(ref_m["loss"]), rel=1e-5)
    assert float(m["grad_norm"]) == pytest.approx(float(ref_m["grad_norm"]), rel=1e-5)
    for a, b in zip(jax.tree.leaves(p), jax.tree.leaves(ref_p)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
