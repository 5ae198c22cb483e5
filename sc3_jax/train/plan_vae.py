"""The Wan VAE tokenizers as the planner sees them (``plan.py``): the VAE is never allocated. Its geometry (grid,
token_dim, 4x time compression) comes from its preset or its checkpoint's config.json; while a plan is made its
encode / decode stand in as zeros of the real shapes (``shape_only_vae``), so the DiT's programs lower alone; the
VAE's own FLOPs are the lowered cost of ``wan_vae.encode_moments`` / ``decode`` on abstract weights
(``vae_costs``), reported beside the DiT's."""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
from pathlib import Path

from sc3_jax.core import xla_cost
from sc3_jax.core.errors import UserError

WAN = ("wan2.1", "wan2.2")


@functools.lru_cache(maxsize=8)
def vae_config(model_cfg):
    """The Wan VAE architecture of a model config: its checkpoint's config.json (the weights are not read), or the
    preset where model.tokenizer_path is unset or not on this machine (a plan is often made where the weights are
    not; ``vae_note`` says so)."""
    from sc3_jax.model import wan_vae, wan_vae_convert

    path = Path(model_cfg.tokenizer_path or "") / "config.json"
    if not model_cfg.tokenizer_path or not path.parent.exists():
        return wan_vae.PRESETS[model_cfg.tokenizer]()
    if not path.is_file():
        raise UserError(f"model.tokenizer_path={model_cfg.tokenizer_path}: no config.json there (a diffusers "
                        "AutoencoderKLWan directory)")
    vae = wan_vae_convert.config_from_diffusers(json.loads(path.read_text()))
    if vae.is_residual != (model_cfg.tokenizer == "wan2.2"):
        raise UserError(f"model.tokenizer_path={model_cfg.tokenizer_path} holds a "
                        f"{'wan2.2' if vae.is_residual else 'wan2.1'}-style VAE, model.tokenizer is "
                        f"{model_cfg.tokenizer}")
    return vae


def vae_note(model_cfg) -> str | None:
    """Which VAE architecture was planned, where it is not the checkpoint's own."""
    if model_cfg.tokenizer not in WAN or (model_cfg.tokenizer_path and Path(model_cfg.tokenizer_path).exists()):
        return None
    where = (f"model.tokenizer_path {model_cfg.tokenizer_path} is not on this machine" if model_cfg.tokenizer_path
             else "no model.tokenizer_path")
    return f"{where}: the {model_cfg.tokenizer} preset's architecture was planned (the weights are never read)"


def abstract_vae_params(vae):
    import jax
    import jax.numpy as jnp

    from sc3_jax.model import wan_vae

    return jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, jnp.dtype(vae.param_dtype)), wan_vae.param_specs(vae),
                        is_leaf=wan_vae._is_spec)


@functools.lru_cache(maxsize=4)
def _shape_only_wan(vae, patch_size: int):
    """A WanTokenizer with abstract weights whose encode / decode give zeros of the real output shapes (traced
    through the real VAE by ``jax.eval_shape``, so a shape the VAE refuses is refused here too)."""
    import jax
    import jax.numpy as jnp

    from sc3_jax.model.wan_tokenizer import WanTokenizer

    class ShapeOnlyWan(WanTokenizer):
        def encode_with(self, params, frames):
            out = jax.eval_shape(lambda p, f: WanTokenizer.encode_with(self, p, f), self.params,
                                 jax.ShapeDtypeStruct(frames.shape, frames.dtype))
            return jnp.zeros(out.shape, out.dtype)

        def decode_with(self, params, tokens, image_size, clamp: bool = True):
            out = jax.eval_shape(lambda p, t: WanTokenizer.decode_with(self, p, t, image_size, clamp), self.params,
                                 jax.ShapeDtypeStruct(tokens.shape, tokens.dtype))
            return jnp.zeros(out.shape, out.dtype)

    return ShapeOnlyWan(vae, abstract_vae_params(vae), patch_size)


@contextlib.contextmanager
def shape_only_vae(cfg):
    """While planning ``cfg``, ``model.tokenizer`` "wan2.1" / "wan2.2" resolves to the shape-only tokenizer: the
    train step and the rollout chunk lower without the VAE's weights (0.1-0.7B parameters) ever being allocated.
    (tokenizer.make_tokenizer imports wan_tokenizer.make_wan_tokenizer at each call, so this one name is the hook.)"""
    if cfg.model.tokenizer not in WAN:
        yield
        return
    from unittest import mock

    from sc3_jax.model import wan_tokenizer

    def make(name, path=None, patch_size=1, batch_size=None, seed=0, **overrides):
        return _shape_only_wan(vae_config(dataclasses.replace(cfg.model, tokenizer=name, tokenizer_path=path)),
                               patch_size)

    with mock.patch.object(wan_tokenizer, "make_wan_tokenizer", make):
        yield


def vae_costs(cfg) -> dict | None:
    """The Wan VAE's share, from abstract weights (None for other tokenizers): weight bytes (all; the encoder's,
    which the train step holds as constants), the FLOPs of encoding one view's window and of one rollout chunk's
    encode (the K context frames) and decode (every token frame: the causal decoder needs the context's).
    The VAE runs a ``lax.scan`` over 4-frame chunks (one latent frame each when decoding), which a cost analysis
    counts once: the count is first chunk + n x one more chunk, each lowered on its own."""
    if cfg.model.tokenizer not in WAN:
        return None
    import jax
    import jax.numpy as jnp

    from sc3_jax.model import wan_vae
    from sc3_jax.model.tokenizer import make_tokenizer, window_tokens

    vae = vae_config(cfg.model)
    params = abstract_vae_params(vae)
    H, W = cfg.data.image_size
    h, w = H // vae.spatial_ratio, W // vae.spatial_ratio
    sds = jax.ShapeDtypeStruct
    enc = jax.jit(lambda p, v: wan_vae.encode_moments(p, vae, v))
    dec = jax.jit(lambda p, z: wan_vae.decode(p, vae, z))

    ce = [xla_cost.flops(enc.trace(params, sds((1, f, H, W, 3), jnp.float32)).lower(), False)
          for f in (1, 1 + wan_vae.CHUNK)]
    cd = [xla_cost.flops(dec.trace(params, sds((1, f, h, w, vae.z_dim), jnp.float32)).lower(), False) for f in (1, 2)]

    def encode(frames: int) -> float:  # one video of ``frames`` frames: the first, then chunks of 4
        return ce[0] + (frames - 1) // wan_vae.CHUNK * (ce[1] - ce[0])

    def decode(latent_frames: int) -> float:  # one video of ``latent_frames`` token frames, one per chunk
        return cd[0] + (latent_frames - 1) * (cd[1] - cd[0])

    def nbytes(tree):
        return float(sum(math.prod(x.shape) * x.dtype.itemsize for x in jax.tree.leaves(tree)))

    d = cfg.data
    with shape_only_vae(cfg):
        Kt, Tt = window_tokens(make_tokenizer(cfg.model), d.context_frames, d.future_frames)
    return {"name": cfg.model.tokenizer, "weights_bytes": nbytes(params),
            "encoder_bytes": nbytes({k: params[k] for k in ("encoder", "quant_conv")}),
            # per video (one view): its training window encoded, a rollout chunk's context encoded and its window
            # of token frames decoded
            "video_window_encode_flops": encode(d.context_frames + d.future_frames),
            "video_context_encode_flops": encode(d.context_frames), "video_decode_flops": decode(Kt + Tt),
            "spatial_ratio": vae.spatial_ratio, "temporal_ratio": vae.temporal_ratio, "precision": vae.precision,
            "dtype": vae.dtype}
