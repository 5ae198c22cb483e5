"""``checkpoint.save(dtype="int8")``: matrices as int8 with per-output-channel scales, read back transparently by
every loader, within half a quantisation step of the original, and smaller than the float16 export."""
import jax
import numpy as np

from sc3_jax.model import checkpoint
from sc3_jax.core.config import Config, DataConfig, ModelConfig
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.model import dit


def test_quantize_int8_error_is_half_a_step_per_channel():
    w = np.random.default_rng(0).normal(size=(3, 64, 32)).astype(np.float32)
    w[1, :, 5] *= 100.0  # one loud channel of one layer must not coarsen the others
    q, scale = checkpoint.quantize_int8(w)
    assert q.dtype == np.int8 and scale.shape == (3, 1, 32)
    err = np.abs(q * scale.astype(np.float32) - w)
    assert np.all(err <= 0.5 * scale.astype(np.float32) + 1e-3 * np.abs(w))
    assert scale[1, 0, 5] > 50 * scale[1, 0, 4]


def test_int8_export_loads_close_and_smaller(tmp_path):
    cfg = Config(model=ModelConfig(dim=64, depth=2, num_heads=2, num_kv_heads=1, head_dim=32, mlp_dim=128,
                                   rope_axes_dim=(6, 5, 5)),
                 data=DataConfig(image_size=(16, 16), context_frames=1, future_frames=2))
    shapes = checkpoint.param_shapes(cfg)
    params = jax.tree.map(lambda s: np.random.default_rng(s.size).normal(size=s.shape).astype(np.float32) * 0.05,
                          shapes)
    stats = NormStats.from_actions(np.random.default_rng(1).normal(size=(50, 7)).astype(np.float32))
    f16 = checkpoint.save(tmp_path / "f16", cfg, stats, params)
    i8 = checkpoint.save(tmp_path / "i8", cfg, stats, params, "int8")
    assert (i8 / "params.npz").stat().st_size < 0.75 * (f16 / "params.npz").stat().st_size
    assert checkpoint.source_shapes(i8) == checkpoint.source_shapes(f16)  # scales are not params
    _, _, back = checkpoint.load(i8)
    ref = jax.tree.leaves(params)
    got = [np.asarray(x) for x in jax.tree.leaves(back)]
    quantised = 0
    for a, b in zip(ref, got):
        assert a.shape == b.shape and b.dtype == np.float32
        bound = np.abs(a).max() / 127 if a.ndim >= 2 and a.size >= checkpoint.INT8_MIN_SIZE else 1e-3
        np.testing.assert_allclose(b, a, atol=bound)
        quantised += a.ndim >= 2 and a.size >= checkpoint.INT8_MIN_SIZE
    assert quantised > 0
