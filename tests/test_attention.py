"""Memory-efficient attention (sc3_jax/model/attention.py): the blockwise (flash) kernel equals dense attention,
outputs and gradients in fp32, for every mask the model uses -- in the kernel, in dit.apply, in cached-context
sampling and in inverse-mode caching, with and without the text pathway; the cuDNN path is chosen only where it
can run; compiled memory grows linearly with the sequence instead of quadratically."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.model import flow, modes
from sc3_jax.core.config import ModelConfig
from sc3_jax.model import attention, attention_impl, dit, layers, tokenizer


def _qkv(B, N, M, hq=4, hkv=2, d=8, dtype=jnp.float32):
    ks = jax.random.split(jax.random.key(0), 4)
    return tuple(jax.random.normal(k, s).astype(dtype) for k, s in zip(
        ks, ((B, N, hq, d), (B, M, hkv, d), (B, M, hkv, d), (B, N, hq, d))))


def _mask(kind, B, N, M):
    if kind == "full":
        return None
    if kind == "causal_context":  # dit's causal context attention, queries = the last N of the M tokens
        noisy = jax.random.bernoulli(jax.random.key(5), 0.5, (B, M))
        seg = attention.causal_segments(noisy, M // 4)
        return attention.SegmentMask(seg[:, M - N:], seg, attention.CAUSAL_TABLE)
    if kind == "text_prefix":  # the same, behind 7 text keys every query sees
        noisy = jax.random.bernoulli(jax.random.key(5), 0.5, (B, M - 7))
        seg = attention.causal_segments(noisy, (M - 7) // 4)
        return attention.with_prefix(attention.SegmentMask(seg[:, M - 7 - N:], seg, attention.CAUSAL_TABLE), 7)
    if kind == "causal":  # the text pathway among its own tokens
        return attention.causal_mask()
    if kind == "table":  # an arbitrary table with a query segment that sees nothing (fully masked rows)
        table = ((True, False, True), (False, True, False), (False, False, False))
        return attention.SegmentMask(jax.random.randint(jax.random.key(6), (B, N), 0, 3),
                                     jax.random.randint(jax.random.key(7), (B, M), 0, 3), table)
    raise ValueError(kind)


def _out_and_grads(fn, q, k, v, ct):
    def f(q, k, v):
        out = fn(q, k, v)
        return jnp.sum(out * ct), out
    (_, out), grads = jax.jit(jax.value_and_grad(f, argnums=(0, 1, 2), has_aux=True))(q, k, v)
    return out, grads


@pytest.mark.parametrize("kind,N,M", [("full", 37, 45), ("causal_context", 37, 45), ("causal_context", 45, 45),
                                      ("text_prefix", 30, 45), ("causal", 40, 40), ("table", 37, 45)])
def test_blockwise_matches_dense(kind, N, M):
    """Several query and key tiles (block 8), neither length a multiple of the block (padded last tile),
    grouped kv heads."""
    q, k, v, ct = _qkv(2, N, M)
    mask = _mask(kind, 2, N, M)
    ref = _out_and_grads(lambda q, k, v: attention_impl.attend("dense", q, k, v, mask), q, k, v, ct)
    got = _out_and_grads(lambda q, k, v: attention.blockwise(q, k, v, mask, block=8), q, k, v, ct)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(ref)):
        np.testing.assert_allclose(a, b, atol=2e-6, rtol=1e-5)


def test_log_sum_exp_and_padding_segment():
    """The log-sum-exp output (what ring attention merges by) and its gradient equal the dense logsumexp; keys of
    segment -1 are padding, attended by no query (not even a fully masked one)."""
    B, N, M = 2, 20, 26
    q, k, v, ct = _qkv(B, N, M)
    mask = _mask("table", B, N, M)
    pad = jnp.arange(M) >= M - 5
    padded = attention.SegmentMask(mask.q, jnp.where(pad, -1, mask.k), mask.table)

    def dense_lse(q, k):
        kk = jnp.repeat(k, 2, axis=2)
        s = jnp.einsum("bnhd,bmhd->bnhm", q, kk) / np.sqrt(q.shape[-1])
        s = jnp.where(mask.allowed()[:, :, None, :], s, attention.MASKED)
        return jax.nn.logsumexp(s, axis=-1)

    w = jax.random.normal(jax.random.key(9), (B, N, 4))
    got = jax.value_and_grad(lambda q, k: jnp.sum(attention.blockwise_lse(q, k, v, mask, 8)[1] * w),
                             argnums=(0, 1))(q, k)
    ref = jax.value_and_grad(lambda q, k: jnp.sum(dense_lse(q, k) * w), argnums=(0, 1))(q, k)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(ref)):
        np.testing.assert_allclose(a, b, atol=1e-4, rtol=1e-5)
    out = attention.blockwise(q, k, v, padded, block=8)
    np.testing.assert_allclose(out, attention_impl.attend("dense", q[:, :], k[:, :M - 5], v[:, :M - 5],
                                                     attention.SegmentMask(mask.q, mask.k[:, :M - 5], mask.table)),
                               atol=2e-6)


# ----------------------------------------------------------------------------------------------------------------
# The cuDNN path: selected only where it can run
# ----------------------------------------------------------------------------------------------------------------
def test_fused_selection():
    q, k, _, _ = _qkv(1, 16, 16, dtype=jnp.bfloat16)
    seg = _mask("causal_context", 1, 16, 16)
    assert attention.fused_ok(q, k, None, backend="gpu")
    assert attention.fused_ok(q, k, attention.causal_mask(), backend="gpu")  # the text pathway
    assert attention.fused_ok(q, k, attention.full_mask(1, 16, 16), backend="gpu")  # an all-True table
    assert not attention.fused_ok(q, k, seg, backend="gpu")  # a segment table needs a dense bias: blockwise
    assert not attention.fused_ok(q, k, None, backend="cpu")
    assert not attention.fused_ok(q, k, None, backend="tpu")
    assert not attention.fused_ok(q.astype(jnp.float32), k.astype(jnp.float32), None, backend="gpu")
    q256, k256, _, _ = _qkv(1, 16, 16, d=256, dtype=jnp.bfloat16)
    assert not attention.fused_ok(q256, k256, None, backend="gpu")  # head_dim > 128
    q8, k8, _, _ = _qkv(1, 8, 16, dtype=jnp.bfloat16)
    assert not attention.fused_ok(q8, k8, attention.causal_mask(), backend="gpu")  # causal with a cached prefix


def test_fused_falls_back_to_blockwise_off_gpu(monkeypatch):
    q, k, v, _ = _qkv(2, 24, 24, dtype=jnp.bfloat16)
    ref = attention.blockwise(q, k, v, None, block=8)
    calls = []
    monkeypatch.setattr(attention, "fused", lambda *a: calls.append(a) or jnp.zeros_like(a[0]))
    np.testing.assert_array_equal(attention_impl.attend("fused", q, k, v, None, block=8), ref)  # CPU: blockwise
    assert not calls
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")  # as on a GPU: the full mask goes to cuDNN ...
    attention_impl.attend("fused", q, k, v, None, block=8)
    assert len(calls) == 1
    mask = _mask("causal_context", 2, 24, 24)  # ... a segment mask does not
    np.testing.assert_array_equal(attention_impl.attend("fused", q, k, v, mask, block=8),
                                  attention.blockwise(q, k, v, mask, block=8))
    assert len(calls) == 1


# ----------------------------------------------------------------------------------------------------------------
# The model: forward, gradients, cached-context sampling, inverse-mode caching, text pathway
# ----------------------------------------------------------------------------------------------------------------
B, V, K, T, H = 2, 2, 2, 3, 8  # 4 tokens per frame: 2 views x 5 frames x 4 + 3 actions = 43 tokens (block 16)


def _model(context_attention, cosmos=False, **kw):
    extra = dict(layout="cosmos3", text_pathway=True, vocab_size=50, view_embedding=False) if cosmos else {}
    cfg = ModelConfig(dim=32, depth=2, num_heads=4, num_kv_heads=2, head_dim=16, mlp_dim=64, rope_axes_dim=(4, 2, 2),
                      num_views=V, prediction="velocity", context_attention=context_attention, attention_block=16,
                      **extra, **kw)
    tok = tokenizer.PixelPatchTokenizer(4)
    shapes = jax.eval_shape(lambda: dit.init_params(cfg, tok.token_dim, jax.random.key(0), tok.grid((H, H))))
    rng = np.random.default_rng(0)  # random everything (also the zero-initialised weights): outputs see all params
    params = jax.tree.map(lambda x: (rng.normal(size=x.shape) / np.sqrt(x.shape[-1])).astype(np.float32), shapes)
    return cfg, tok, params


def _inputs(tok, mode, text=False):
    rng = np.random.default_rng(1)
    video = tok.encode(rng.integers(0, 256, (B, V, K + T, H, H, 3)).astype(np.uint8))
    actions = rng.normal(size=(B, T, 7)).astype(np.float32)
    vn, an = modes.fixed(mode, B, V, K, T)
    inp = flow.noise_inputs(video, actions, jnp.asarray([1, 2]), vn, an, jnp.asarray([0.3, 0.8]),
                            rng.normal(size=video.shape).astype(np.float32),
                            rng.normal(size=actions.shape).astype(np.float32))
    return inp._replace(text=jnp.asarray(rng.integers(0, 50, (B, 5)), jnp.int32)) if text else inp


def _with(cfg, **kw):
    return dataclasses.replace(cfg, **kw)


def _apply_and_grads(cfg, params, inp, grid):
    def loss(p):
        out_v, out_a = dit.apply(p, cfg, inp, grid)
        return jnp.sum(out_v * jnp.cos(out_v)) + jnp.sum(out_a ** 2), (out_v, out_a)
    (_, outs), grads = jax.jit(jax.value_and_grad(loss, has_aux=True))(params)
    return outs, grads


def _assert_close(got, ref, atol):
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(ref)):
        np.testing.assert_allclose(a, b, atol=atol, rtol=1e-4)


@pytest.mark.parametrize("context_attention,cosmos", [("full", False), ("causal", False), ("causal", True)])
def test_dit_apply_and_grads_match_dense(context_attention, cosmos):
    """Outputs and the gradient of every parameter (text pathway's included) equal the dense model's; remat
    ("dots" keeps the weight matmuls, "block" only layer inputs) changes nothing but memory."""
    cfg, tok, params = _model(context_attention, cosmos)
    grid = tok.grid((H, H))
    inp = _inputs(tok, modes.FD, text=cosmos)
    ref = _apply_and_grads(cfg, params, inp, grid)
    for impl, remat in (("blockwise", "none"), ("fused", "dots"), ("blockwise", "block")):
        _assert_close(_apply_and_grads(_with(cfg, attention_impl=impl, remat=remat), params, inp, grid), ref, 1e-5)


@pytest.mark.parametrize("cosmos", [False, True])
def test_cached_context_and_inverse_mode_match_dense(cosmos):
    """Rollout paths: forward dynamics with the context's keys/values cached, inverse dynamics with every video
    token cached (only the action tokens are queries), the text prefix cached with text_kv."""
    cfg, tok, params = _model("causal", cosmos)
    blk = _with(cfg, attention_impl="blockwise")
    grid = tok.grid((H, H))

    def run(c, inp, prefix):
        tkv = dit.encode_text(params, c, inp.text) if cosmos else None
        kv = dit.encode_context(params, c, inp, grid, prefix=prefix, text_kv=tkv)
        return kv, dit.apply_cached(params, c, inp, grid, kv, text_kv=tkv), tkv

    for mode, prefix in ((modes.FD, "context"), (modes.ID, "video")):
        inp = _inputs(tok, mode, text=cosmos)
        ref = jax.jit(lambda i: run(cfg, i, prefix))(inp)
        got = jax.jit(lambda i: run(blk, i, prefix))(inp)
        _assert_close(got, ref, 2e-5)
        full = jax.jit(lambda i: dit.apply(params, cfg, i, grid))(inp)  # cached = uncached (inverse: actions only)
        _assert_close(got[1] if prefix == "context" else got[1][1], full if prefix == "context" else full[1], 2e-5)


def test_config_values():
    assert ModelConfig(remat=True).remat == "block" and ModelConfig(remat=False).remat == "none"
    assert ModelConfig(remat="dots").remat == "dots"
    with pytest.raises(ValueError, match="remat"):
        ModelConfig(remat="all")
    with pytest.raises(ValueError, match="attention_impl"):
        ModelConfig(attention_impl="flash")
    with pytest.raises(ValueError, match="attention_block"):
        ModelConfig(attention_block=0)


# ----------------------------------------------------------------------------------------------------------------
# Memory
# ----------------------------------------------------------------------------------------------------------------
def _grad_temp_bytes(impl, N):
    q, k, v, _ = _qkv(1, N, N, hq=2, hkv=1, d=16)
    mask = _mask("causal_context", 1, N, N)
    f = jax.grad(lambda q, k, v: jnp.sum(attention_impl.attend(impl, q, k, v, mask, block=128) ** 2), argnums=(0, 1, 2))
    return jax.jit(f).lower(q, k, v).compile().memory_analysis().temp_size_in_bytes


def test_blockwise_memory_grows_linearly():
    """Compiled forward + backward temp memory at N and 2N tokens: dense ~4x (scores [N, N]), blockwise ~2x."""
    dense = _grad_temp_bytes("dense", 2048) / _grad_temp_bytes("dense", 1024)
    blockwise = _grad_temp_bytes("blockwise", 2048) / _grad_temp_bytes("blockwise", 1024)
    assert dense > 3.5 and blockwise < 2.5, (dense, blockwise)
