"""The chunk account (bench/chunk_account.py, ``flops.chunk_account``) at a small size with the paper config's
structure (3 views, K = 4, l' = 24, causal context attention, pixel patches, 10 + 10 Euler steps): the compiled FLOPs
of one rollout chunk stay within 1.3x of the ideal count, which the sampler without the context cache
does not."""
import pytest

from sc3_jax.train import flops
from sc3_jax.core.config import MeshConfig, load_config, replace
from sc3_jax.data.action_space import DELTA_EE

BOUND = 1.3


@pytest.fixture(scope="module")
def cfg():
    return replace(load_config("paper"), model=dict(dim=128, depth=2, num_heads=4, num_kv_heads=2, head_dim=32,
                                                    mlp_dim=512, rope_axes_dim=(6, 5, 5), patch_size=8,
                                                    dtype="float32"),
                   data=dict(image_size=(32, 32)), mesh=MeshConfig(1, 1, 1))


def test_a_chunk_compiles_to_within_1_3x_of_the_ideal_flops(cfg):
    a = flops.chunk_account(cfg, action_space=DELTA_EE, data_fps=20.0)
    parts = a["parts"]
    assert a["counted_depths"] == (2,) and a["steps"] == (10, 10)
    assert parts["forward step"]["runs"] == 10 and parts["inverse step"]["runs"] == 10
    # the whole model step holds nothing the parts do not (RNG, integration and U are noise against the DiT)
    assert a["chunk_flops"] == pytest.approx(a["parts_flops"], rel=0.01)
    assert a["ratio"] == pytest.approx(a["chunk_flops"] / a["ideal_flops"])
    assert 1.0 <= a["ratio"] <= BOUND
    # each Euler step runs its noisy tokens only: an inverse step is a sliver of a forward one
    assert parts["inverse step"]["flops"] < 0.05 * parts["forward step"]["flops"]
    for name in ("forward step", "inverse step"):
        assert parts[name]["flops"] <= BOUND * parts[name]["ideal_flops"], name


def test_the_bound_fails_without_the_context_cache(cfg):
    a = flops.chunk_account(cfg, cache=False, action_space=DELTA_EE, data_fps=20.0)
    assert a["parts"]["context encoding"]["flops"] == 0 and a["parts"]["inverse encoding"]["flops"] == 0
    assert a["ratio"] > 1.5 * BOUND  # every Euler step runs every token, an inverse one ~100x its noisy ones


@pytest.mark.slow  # 25-55 s: kept out of the default run's 15 minutes (CI runs -m slow too)
def test_the_inverse_sampler_extending_the_forward_samplers_context_cache_reads_the_same_actions(cfg):
    """What removed the account's one excess (the inverse encoding re-ran the context): exact up to float noise."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from sc3_jax.model import flow, modes
    from sc3_jax.model import dit
    from sc3_jax.model.tokenizer import make_tokenizer

    m, (K, T) = cfg.model, (cfg.data.context_frames, cfg.data.future_frames)
    tok = make_tokenizer(m)
    grid = tok.grid(cfg.data.image_size)
    params = dit.init_params(m, tok.token_dim, jax.random.key(0), grid)
    video = jax.random.normal(jax.random.key(1), (1, 3, K + T, grid[0] * grid[1], tok.token_dim))
    actions, stride = jnp.zeros((1, T, m.action_dim)), jnp.full((1,), 2, jnp.int32)
    kv = flow.context_cache(params, m, video, actions, stride, *modes.fixed(modes.FD, 1, 3, K, T), grid,
                            context_frames=K)
    ids = (video, actions, stride, *modes.fixed(modes.ID, 1, 3, K, T), jax.random.key(2), 2, grid)
    ref = flow.sample(params, m, *ids, cache="video", context_frames=K)[1]
    np.testing.assert_allclose(flow.sample(params, m, *ids, cache="video", context_frames=K, context_kv=kv)[1], ref,
                               atol=1e-5)
