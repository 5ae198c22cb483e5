"""A small convolutional autoencoder for low-resolution robot views: the learned latent space the world model
works in (``model.tokenizer = "conv_ae"``).

Why: a linear read-out of 16-px pixel patches cannot draw a thin arm, so a world model on pixel patches blurs the
robot away. Every robot evaluator with good correlation runs on learned latents; at 64x64 a small CNN trained to
near-perfect reconstruction is enough (the Interactive World Simulator does the same at 4x downsampling).

Shape (per view and frame, NHWC): uint8 [H, W, 3] -> latents float32 [H/f, W/f, C] -> [-1, 1] images.
Most of the compute sits at the latent resolution: the encoder starts with a space-to-depth of the full image
(every 2x2 pixel block stacked into channels, a lossless reshape) so no convolution runs at full resolution, and
the decoder ends in a depth-to-space (pixel shuffle) followed by one narrow full-resolution convolution that fixes
the block seams. On 2 CPU cores this trains ~4x faster than strided convolutions from full resolution at the same
reconstruction quality (see docs/world_model.md for the measurement).

Latents are standardised per channel with statistics measured on the training data (``AEParams.stats``), so the
rectified flow's unit-variance noise has the right scale for every channel.

Parameters are a plain dict of arrays (``init``); ``encode`` / ``decode`` are pure and jit/vmap-safe.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.core.errors import UserError
from sc3_jax.core.tokenizer_config import AEConfig  # the architecture; ae.AEConfig for callers


# -- layers -------------------------------------------------------------------------------------------------------
def _conv_init(key, k: int, cin: int, cout: int, scale: float = 1.0) -> dict:
    w = jax.random.normal(key, (k, k, cin, cout), jnp.float32) * (scale / math.sqrt(k * k * cin))
    return {"w": w, "b": jnp.zeros((cout,), jnp.float32)}


def _conv(p: dict, x: jax.Array) -> jax.Array:
    k = p["w"].shape[0]
    y = jax.lax.conv_general_dilated(x, p["w"].astype(x.dtype), (1, 1), [(k // 2, k // 2)] * 2,
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return y + p["b"].astype(x.dtype)


def _res_init(key, c: int) -> dict:
    k1, k2 = jax.random.split(key)
    return {"c1": _conv_init(k1, 3, c, c), "c2": _conv_init(k2, 3, c, c, scale=0.1)}


def _res(p: dict, x: jax.Array) -> jax.Array:
    return x + _conv(p["c2"], jax.nn.silu(_conv(p["c1"], jax.nn.silu(x))))


def space_to_depth(x: jax.Array, f: int) -> jax.Array:
    n, h, w, c = x.shape
    x = x.reshape(n, h // f, f, w // f, f, c)
    return x.transpose(0, 1, 3, 2, 4, 5).reshape(n, h // f, w // f, f * f * c)


def depth_to_space(x: jax.Array, f: int) -> jax.Array:
    n, h, w, c = x.shape
    x = x.reshape(n, h, w, f, f, c // (f * f))
    return x.transpose(0, 1, 3, 2, 4, 5).reshape(n, h * f, w * f, c // (f * f))


# -- model --------------------------------------------------------------------------------------------------------
def init(cfg: AEConfig, key: jax.Array) -> dict:
    """Random parameters. Encoder: space-to-depth 2x, then (conv, space-to-depth 2x) per further level, residual
    blocks and a 1x1 projection to ``latent_channels`` at the latent resolution; the decoder mirrors it with pixel
    shuffles."""
    ks = iter(jax.random.split(key, 64))
    L, W, M, C = cfg.levels, cfg.width, cfg.mid_width, cfg.latent_channels
    enc = {"stem": _conv_init(next(ks), 3, 12, M if L > 1 else W)}
    enc["down"] = [_conv_init(next(ks), 3, 4 * M, M if i < L - 2 else W) for i in range(L - 1)]
    enc["blocks"] = [_res_init(next(ks), W) for _ in range(cfg.blocks)]
    enc["out"] = _conv_init(next(ks), 1, W, C)
    dec = {"inp": _conv_init(next(ks), 3, C, W)}
    dec["blocks"] = [_res_init(next(ks), W) for _ in range(cfg.blocks)]
    # each up level: conv to 4x channels, pixel shuffle 2x
    dec["up"] = [_conv_init(next(ks), 3, W if i == 0 else M, 4 * M) for i in range(L - 1)]
    dec["last_up"] = _conv_init(next(ks), 3, W if L == 1 else M, 4 * cfg.out_width)
    dec["refine"] = _res_init(next(ks), cfg.out_width)
    dec["out"] = _conv_init(next(ks), 3, cfg.out_width, 3)
    return {"enc": enc, "dec": dec}


def encode_raw(params: dict, x: jax.Array) -> jax.Array:
    """[N, H, W, 3] in [-1, 1] -> unstandardised latents [N, H/f, W/f, C]."""
    p = params["enc"]
    h = _conv(p["stem"], space_to_depth(x, 2))
    for d in p["down"]:
        h = _conv(d, space_to_depth(jax.nn.silu(h), 2))
    for b in p["blocks"]:
        h = _res(b, h)
    return _conv(p["out"], jax.nn.silu(h))


def decode_raw(params: dict, z: jax.Array) -> jax.Array:
    """Unstandardised latents [N, h, w, C] -> images [N, h f, w f, 3] (unbounded; ~[-1, 1])."""
    p = params["dec"]
    h = _conv(p["inp"], z)
    for b in p["blocks"]:
        h = _res(b, h)
    for u in p["up"]:
        h = depth_to_space(_conv(u, jax.nn.silu(h)), 2)
    h = depth_to_space(_conv(p["last_up"], jax.nn.silu(h)), 2)
    h = _res(p["refine"], h)
    return _conv(p["out"], jax.nn.silu(h))


def _flat(fn, x, trailing: int = 3):
    lead = x.shape[:-trailing]
    y = fn(x.reshape((-1,) + x.shape[-trailing:]))
    return y.reshape(lead + y.shape[1:])


def encode(params: dict, stats: dict, frames: jax.Array) -> jax.Array:
    """uint8 (or [-1, 1] float) [..., H, W, 3] -> standardised latents [..., h, w, C]."""
    x = frames.astype(jnp.float32) / 127.5 - 1.0 if frames.dtype == jnp.uint8 else frames
    z = _flat(lambda v: encode_raw(params, v), x)
    return (z - stats["mean"]) / stats["std"]


def decode(params: dict, stats: dict, latents: jax.Array) -> jax.Array:
    """Standardised latents [..., h, w, C] -> images [..., H, W, 3] in [-1, 1] (clipped)."""
    z = latents * stats["std"] + stats["mean"]
    return jnp.clip(_flat(lambda v: decode_raw(params, v), z), -1.0, 1.0)


def count(params) -> int:
    return int(sum(np.prod(x.shape) for x in jax.tree.leaves(params)))


# -- files ---------------------------------------------------------------------------------------------------------
# A trained autoencoder is a directory: ae.json ({"config": AEConfig fields, "image_size": [H, W]}) and
# ae_params.npz (flattened params with "/"-joined keys, plus "stats/mean" and "stats/std").
def _flatten(tree, prefix=""):
    out = {}
    if isinstance(tree, dict):
        for k, v in tree.items():
            out.update(_flatten(v, f"{prefix}{k}/"))
    elif isinstance(tree, (list, tuple)):
        for i, v in enumerate(tree):
            out.update(_flatten(v, f"{prefix}{i}/"))
    else:
        out[prefix[:-1]] = np.asarray(tree)
    return out


def _unflatten(flat: dict, like):
    def build(t, prefix):
        if isinstance(t, dict):
            return {k: build(v, f"{prefix}{k}/") for k, v in t.items()}
        if isinstance(t, (list, tuple)):
            return [build(v, f"{prefix}{i}/") for i, v in enumerate(t)]
        key = prefix[:-1]
        if key not in flat:
            raise KeyError(f"autoencoder file lacks parameter {key!r}")
        if tuple(flat[key].shape) != tuple(t.shape):
            raise ValueError(f"autoencoder parameter {key!r}: shape {flat[key].shape}, config expects {t.shape}")
        return np.asarray(flat[key], np.float32)
    return build(like, "")


def save(directory: str | Path, cfg: AEConfig, image_size, params: dict, stats: dict,
         dtype=np.float32) -> None:
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    flat = {k: v.astype(dtype) for k, v in _flatten(params).items()}
    flat["stats/mean"] = np.asarray(stats["mean"], np.float32)
    flat["stats/std"] = np.asarray(stats["std"], np.float32)
    from sc3_jax.core import atomic  # ae.json last: a directory with it holds whole params
    atomic.save_npz(d / "ae_params.npz", compressed=False, **flat)
    atomic.write_json(d / "ae.json", {"config": dataclasses.asdict(cfg), "image_size": list(image_size)})


def load(directory: str | Path) -> tuple[AEConfig, tuple[int, int], dict, dict]:
    """(config, image_size, params, stats) of a saved autoencoder directory, as numpy arrays: a tokenizer may first
    be built while a jit is tracing (and is cached), so nothing here may become a traced value."""
    d = Path(directory)
    if not (d / "ae.json").exists():
        raise FileNotFoundError(f"{d}: no ae.json (train one with `sc3 train-tokenizer`)")
    from sc3_jax.core import atomic
    from sc3_jax.model.saved_model import AE_FIX, read_ae

    cfg, image_size = read_ae(d)  # every field checked: a retyped one was a JAX TypeError once traced
    with atomic.open_npz(d / "ae_params.npz", AE_FIX) as z:
        flat = {k: z[k] for k in z.files}
    like = jax.eval_shape(lambda: init(cfg, jax.random.key(0)))
    try:
        params = _unflatten(flat, like)
    except (KeyError, ValueError) as e:  # not the params of ae.json's autoencoder
        raise UserError(f"{d / 'ae_params.npz'}: {e.args[0]}; {AE_FIX}") from None
    if "stats/mean" not in flat or "stats/std" not in flat:
        raise UserError(f"{d / 'ae_params.npz'}: no latent statistics (stats/mean, stats/std); {AE_FIX}")
    stats = {k: np.asarray(flat[f"stats/{k}"], np.float32) for k in ("mean", "std")}
    return cfg, image_size, params, stats
