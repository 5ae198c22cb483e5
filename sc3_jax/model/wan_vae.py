"""The Wan video VAE (diffusers ``AutoencoderKLWan``) as pure JAX functions of a plain parameter dict.

Both variants are covered by one config:
  * Wan2.1 style: 8x space, 4x time, ``z_dim`` 16, plain down/up blocks (optionally with attention);
  * Wan2.2 style (``is_residual=True, patch_size=2``): pixels are first space-to-depth patchified (2x2 -> 12
    channels), residual down/up blocks with parameter-free average-down / duplicate-up shortcuts; 16x space,
    4x time, ``z_dim`` 48 (Cosmos3's latent_channel).

Layout. Activations are channels-last ``[B, T, H, W, C]``; conv weights are stored ``[kt, kh, kw, in, out]`` (3-D)
or ``[kh, kw, in, out]`` (2-D, applied frame by frame); RMS-norm gains are ``[C]``. The parameter tree mirrors the
diffusers module tree (``encoder.down_blocks.3.conv1.weight`` -> ``params["encoder"]["down_blocks"]["3"]["conv1"]
["weight"]``), so ``wan_vae_convert`` maps checkpoints key for key; ``param_specs`` is the single table of every
parameter (our shape, the torch shape, the initialiser).

Time. Every 3-D conv is causal in time. Like diffusers, a video is processed in temporal chunks -- the first frame
alone, then chunks of 4 frames (encoder) / one latent frame at a time (decoder) -- with each causal conv carrying
the last two frames of its input (one for a strided temporal downsample) from chunk to chunk. Here that cache is an
explicit pytree threaded through a ``lax.scan`` over chunks: memory is bounded by one chunk whatever the video
length, and the whole thing stays a differentiable pure function. The first chunk is special exactly as in
diffusers: temporal down/upsamplers pass its single frame through without their time conv, and the residual
decoder's duplicate-up shortcut keeps only the last of its copies. So ``T`` frames give ``1 + (T - 1) // 4``
latent frames (trailing frames beyond ``1 + 4k`` are dropped, as diffusers does) and ``t`` latent frames decode to
``1 + 4 (t - 1)`` frames.
"""
from __future__ import annotations

import dataclasses
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

# diffusers' AutoencoderKLWan defaults (Wan2.1 VAE statistics, 16 channels).
WAN21_LATENTS_MEAN = (-0.7571, -0.7089, -0.9113, 0.1075, -0.1745, 0.9653, -0.1517, 1.5508,
                      0.4134, -0.0715, 0.5517, -0.3632, -0.1922, -0.9497, 0.2503, -0.2921)
WAN21_LATENTS_STD = (2.8184, 1.4541, 2.3275, 2.6558, 1.2196, 1.7708, 2.6052, 2.0743,
                     3.2687, 2.1526, 2.8652, 1.5579, 1.6382, 1.1253, 2.8251, 1.9160)

CHUNK = 4  # pixel frames per encoder chunk after the first (diffusers hard-codes 4)


@dataclasses.dataclass(frozen=True)
class WanVAEConfig:
    """Mirrors ``AutoencoderKLWan.__init__`` (``temporal_downsample`` is diffusers' ``temperal_downsample``)."""
    base_dim: int = 96
    decoder_base_dim: int | None = None
    z_dim: int = 16
    dim_mult: tuple[int, ...] = (1, 2, 4, 4)
    num_res_blocks: int = 2
    attn_scales: tuple[float, ...] = ()
    temporal_downsample: tuple[bool, ...] = (False, True, True)
    dropout: float = 0.0  # kept for config fidelity; this port applies no dropout
    latents_mean: tuple[float, ...] | None = WAN21_LATENTS_MEAN
    latents_std: tuple[float, ...] | None = WAN21_LATENTS_STD
    is_residual: bool = False
    in_channels: int = 3  # after patchify (12 for Wan2.2)
    out_channels: int = 3
    patch_size: int | None = None
    scale_factor_temporal: int | None = 4  # informational (diffusers uses them for pipelines / tiling)
    scale_factor_spatial: int | None = 8
    # JAX-only settings
    dtype: str = "float32"  # activation dtype
    param_dtype: str = "float32"
    precision: str = "highest"  # conv/matmul precision ("highest" = true fp32 on GPUs too; "default" allows TF32)
    remat: bool = False  # rematerialise each temporal chunk in the backward pass

    def __post_init__(self):
        for name in ("dim_mult", "attn_scales", "temporal_downsample", "latents_mean", "latents_std"):
            v = getattr(self, name)
            if v is not None and not isinstance(v, tuple):
                object.__setattr__(self, name, tuple(v))
        if len(self.temporal_downsample) != len(self.dim_mult) - 1:
            raise ValueError(f"temporal_downsample needs {len(self.dim_mult) - 1} entries, got "
                             f"{self.temporal_downsample}")
        if sum(self.temporal_downsample) > 2:
            raise ValueError("at most two temporal downsamples (chunks are 4 frames)")
        p2 = (self.patch_size or 1) ** 2
        if self.in_channels % p2 or self.out_channels % p2:
            raise ValueError(f"in/out channels {self.in_channels}/{self.out_channels} must be multiples of "
                             f"patch_size^2 = {p2}")
        for name in ("latents_mean", "latents_std"):
            v = getattr(self, name)
            if v is not None and len(v) != self.z_dim:
                raise ValueError(f"{name} has {len(v)} entries, z_dim is {self.z_dim}")

    # ---- derived sizes ------------------------------------------------------------------------------------
    @property
    def spatial_ratio(self) -> int:
        return 2 ** (len(self.dim_mult) - 1) * (self.patch_size or 1)

    @property
    def temporal_ratio(self) -> int:
        return 2 ** sum(self.temporal_downsample)

    @property
    def pixel_channels(self) -> int:
        """Channels of the input video before patchify (3 for RGB in both variants)."""
        return self.in_channels // (self.patch_size or 1) ** 2

    @property
    def out_pixel_channels(self) -> int:
        return self.out_channels // (self.patch_size or 1) ** 2

    def latent_frames(self, num_frames: int) -> int:
        if num_frames < 1:
            raise ValueError("need at least one frame")
        return 1 + (num_frames - 1) // CHUNK * (CHUNK // self.temporal_ratio)

    def pixel_frames(self, num_latent_frames: int) -> int:
        return 1 + (num_latent_frames - 1) * self.temporal_ratio


def wan21_config(**overrides) -> WanVAEConfig:
    """The Wan2.1 VAE architecture (diffusers' ``AutoencoderKLWan()`` defaults): 8x8x4, z_dim 16."""
    return WanVAEConfig(**overrides)


def wan22_config(**overrides) -> WanVAEConfig:
    """The Wan2.2 (TI2V-5B) VAE architecture: residual blocks, patch 2, 16x16x4, z_dim 48.

    The latent statistics are not shipped with diffusers; they come from the checkpoint's ``config.json``
    (``wan_vae_convert.load_diffusers``). Until then mean 0 / std 1 (identity normalisation)."""
    kw = {"base_dim": 160, "decoder_base_dim": 256, "z_dim": 48, "is_residual": True, "in_channels": 12,
          "out_channels": 12, "patch_size": 2, "scale_factor_spatial": 16,
          "latents_mean": (0.0,) * 48, "latents_std": (1.0,) * 48}
    kw.update(overrides)
    return WanVAEConfig(**kw)


PRESETS = {"wan2.1": wan21_config, "wan2.2": wan22_config}


# ----------------------------------------------------------------------------------------------------------------
# Parameter table
# ----------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ParamSpec:
    shape: tuple[int, ...]  # ours
    torch_shape: tuple[int, ...]  # diffusers'
    kind: str  # "conv" (transpose [O, I, *k] <-> [*k, I, O]), "bias", "gamma" (reshape [C, 1, ...] <-> [C])
    init: str = "normal"  # "normal" (fan-in scaled), "zeros", "ones"
    fan_in: int | None = None


def _conv_spec(cin, cout, k):
    k = tuple(k)
    w = ParamSpec(k + (cin, cout), (cout, cin) + k, "conv", fan_in=cin * int(np.prod(k)))
    return {"weight": w, "bias": ParamSpec((cout,), (cout,), "bias", "zeros")}


def _gamma_spec(dim, images=False):
    return {"gamma": ParamSpec((dim,), (dim, 1, 1) if images else (dim, 1, 1, 1), "gamma", "ones")}


def _res_spec(cin, cout):
    s = {"norm1": _gamma_spec(cin), "conv1": _conv_spec(cin, cout, (3, 3, 3)),
         "norm2": _gamma_spec(cout), "conv2": _conv_spec(cout, cout, (3, 3, 3))}
    if cin != cout:
        s["conv_shortcut"] = _conv_spec(cin, cout, (1, 1, 1))
    return s


def _attn_spec(dim):
    return {"norm": _gamma_spec(dim, images=True), "to_qkv": _conv_spec(dim, 3 * dim, (1, 1)),
            "proj": _conv_spec(dim, dim, (1, 1))}


def _resample_spec(dim, mode, up_out=None):
    up_out = dim // 2 if up_out is None else up_out
    if mode.startswith("upsample"):
        s = {"resample": {"1": _conv_spec(dim, up_out, (3, 3))}}
        if mode == "upsample3d":
            s["time_conv"] = _conv_spec(dim, 2 * dim, (3, 1, 1))
    else:
        s = {"resample": {"1": _conv_spec(dim, dim, (3, 3))}}
        if mode == "downsample3d":
            s["time_conv"] = _conv_spec(dim, dim, (3, 1, 1))
    return s


def _mid_spec(dim):
    return {"resnets": {"0": _res_spec(dim, dim), "1": _res_spec(dim, dim)}, "attentions": {"0": _attn_spec(dim)}}


def encoder_layout(cfg: WanVAEConfig) -> tuple[list[int], list[tuple]]:
    """Channel widths and the encoder's ``down_blocks`` in order, as diffusers builds them."""
    dims = [cfg.base_dim * u for u in (1,) + cfg.dim_mult]
    blocks, scale, last = [], 1.0, len(cfg.dim_mult) - 1
    for i, (cin, cout) in enumerate(itertools.pairwise(dims)):
        if cfg.is_residual:
            blocks.append(("resdown", cin, cout, cfg.temporal_downsample[i] if i != last else False, i != last))
            continue
        for _ in range(cfg.num_res_blocks):
            blocks.append(("res", cin, cout))
            if scale in cfg.attn_scales:
                blocks.append(("attn", cout))
            cin = cout
        if i != last:
            blocks.append(("resample", cout, "downsample3d" if cfg.temporal_downsample[i] else "downsample2d"))
            scale /= 2.0
    return dims, blocks


def decoder_layout(cfg: WanVAEConfig) -> tuple[list[int], list[tuple]]:
    base = cfg.decoder_base_dim or cfg.base_dim
    dims = [base * u for u in (cfg.dim_mult[-1],) + cfg.dim_mult[::-1]]
    up_t = cfg.temporal_downsample[::-1]
    blocks, last = [], len(cfg.dim_mult) - 1
    for i, (cin, cout) in enumerate(itertools.pairwise(dims)):
        if i > 0 and not cfg.is_residual:
            cin //= 2  # Wan2.1's upsamplers halve the channels
        up = i != last
        if cfg.is_residual:
            blocks.append(("resup", cin, cout, up_t[i] if up else False, up))
        else:
            mode = None if not up else ("upsample3d" if up_t[i] else "upsample2d")
            blocks.append(("up", cin, cout, mode))
    return dims, blocks


def param_specs(cfg: WanVAEConfig) -> dict:
    nrb = cfg.num_res_blocks
    dims, blocks = encoder_layout(cfg)
    down = {}
    for k, b in enumerate(blocks):
        if b[0] == "res":
            down[str(k)] = _res_spec(b[1], b[2])
        elif b[0] == "attn":
            down[str(k)] = _attn_spec(b[1])
        elif b[0] == "resample":
            down[str(k)] = _resample_spec(b[1], b[2])
        else:  # resdown
            _, cin, cout, temporal, flag = b
            s = {"resnets": {str(j): _res_spec(cin if j == 0 else cout, cout) for j in range(nrb)}}
            if flag:
                s["downsampler"] = _resample_spec(cout, "downsample3d" if temporal else "downsample2d")
            down[str(k)] = s
    encoder = {"conv_in": _conv_spec(cfg.in_channels, dims[0], (3, 3, 3)), "down_blocks": down,
               "mid_block": _mid_spec(dims[-1]), "norm_out": _gamma_spec(dims[-1]),
               "conv_out": _conv_spec(dims[-1], 2 * cfg.z_dim, (3, 3, 3))}
    ddims, dblocks = decoder_layout(cfg)
    up = {}
    for k, b in enumerate(dblocks):
        _, cin, cout = b[:3]
        s = {"resnets": {str(j): _res_spec(cin if j == 0 else cout, cout) for j in range(nrb + 1)}}
        if b[0] == "up" and b[3] is not None:
            s["upsamplers"] = {"0": _resample_spec(cout, b[3])}
        elif b[0] == "resup" and b[4]:
            s["upsampler"] = _resample_spec(cout, "upsample3d" if b[3] else "upsample2d", up_out=cout)
        up[str(k)] = s
    decoder = {"conv_in": _conv_spec(cfg.z_dim, ddims[0], (3, 3, 3)), "mid_block": _mid_spec(ddims[0]),
               "up_blocks": up, "norm_out": _gamma_spec(ddims[-1]),
               "conv_out": _conv_spec(ddims[-1], cfg.out_channels, (3, 3, 3))}
    return {"encoder": encoder, "quant_conv": _conv_spec(2 * cfg.z_dim, 2 * cfg.z_dim, (1, 1, 1)),
            "post_quant_conv": _conv_spec(cfg.z_dim, cfg.z_dim, (1, 1, 1)), "decoder": decoder}


def _is_spec(x):
    return isinstance(x, ParamSpec)


def init_params(cfg: WanVAEConfig, key: jax.Array) -> dict:
    """Fresh parameters (fan-in scaled normal weights, zero biases, unit gains). One random draw for all
    weights, sliced on the host (per-leaf draws make XLA:CPU compile ~100 threefry kernels). Not jittable."""
    leaves, treedef = jax.tree.flatten(param_specs(cfg), is_leaf=_is_spec)
    dtype = jnp.dtype(cfg.param_dtype)
    sizes = [int(np.prod(s.shape)) if s.init == "normal" else 0 for s in leaves]
    noise = np.asarray(jax.random.normal(key, (sum(sizes),), jnp.float32))
    out, offset = [], 0
    for spec, n in zip(leaves, sizes):
        if spec.init == "zeros":
            w = np.zeros(spec.shape, np.float32)
        elif spec.init == "ones":
            w = np.ones(spec.shape, np.float32)
        else:
            w = noise[offset:offset + n].reshape(spec.shape) / np.float32(math.sqrt(spec.fan_in))
        out.append(jnp.asarray(w, dtype))
        offset += n
    return jax.tree.unflatten(treedef, out)


def param_axes(cfg: WanVAEConfig) -> dict:
    """Logical axis names (all None: the VAE is small enough to replicate)."""
    return jax.tree.map(lambda s: (None,) * len(s.shape), param_specs(cfg), is_leaf=_is_spec)


# ----------------------------------------------------------------------------------------------------------------
# Layers (channels-last)
# ----------------------------------------------------------------------------------------------------------------
def _prec(cfg):
    return {"highest": lax.Precision.HIGHEST, "high": lax.Precision.HIGH, "default": lax.Precision.DEFAULT}[
        cfg.precision]


def _conv(cfg, p, x, stride=(1, 1, 1), pad_hw=((0, 0), (0, 0))):
    """Valid-in-time conv of [B, T, H, W, C]; a 2-D weight [kh, kw, I, O] is applied frame by frame."""
    w = p["weight"].astype(x.dtype)
    if w.ndim == 4:
        w = w[None]
    y = lax.conv_general_dilated(x, w, window_strides=stride, padding=((0, 0),) + tuple(pad_hw),
                                 dimension_numbers=("NDHWC", "DHWIO", "NDHWC"), precision=_prec(cfg))
    return y + p["bias"].astype(x.dtype)


def _rms(x, gamma):
    """diffusers WanRMS_norm: F.normalize over channels (eps 1e-12, in fp32) * sqrt(C) * gamma."""
    xf = x.astype(jnp.float32)
    ss = jnp.sum(xf * xf, axis=-1, keepdims=True)
    xf = xf * lax.rsqrt(jnp.maximum(ss, 1e-24))  # = x / max(||x||, 1e-12), gradient-safe at 0
    return (xf.astype(x.dtype) * (x.shape[-1] ** 0.5)) * gamma.astype(x.dtype)


class _Stream:
    """Threads the temporal caches of one chunk through the network in call order (diffusers' feat_cache /
    feat_idx). Trace-time only: ``old`` is the previous chunk's list (None for the first chunk)."""

    def __init__(self, old, first: bool):
        self.old, self.first, self.new, self.i = old, first, [], 0

    def take(self):
        v = None if self.old is None else self.old[self.i]
        self.i += 1
        return v

    def put(self, v):
        self.new.append(v)


def _causal_conv(cfg, p, x, s: _Stream):
    """3x3x3 causal conv: the last two input frames of the previous chunk (zeros at the start) come first."""
    prev = s.take()
    if prev is None:
        prev = jnp.zeros(x.shape[:1] + (2,) + x.shape[2:], x.dtype)
    xc = jnp.concatenate([prev.astype(x.dtype), x], axis=1)
    s.put(xc[:, -2:])
    return _conv(cfg, p, xc, pad_hw=((1, 1), (1, 1)))


def _resblock(cfg, p, x, s):
    h = _conv(cfg, p["conv_shortcut"], x) if "conv_shortcut" in p else x
    x = _causal_conv(cfg, p["conv1"], jax.nn.silu(_rms(x, p["norm1"]["gamma"])), s)
    x = _causal_conv(cfg, p["conv2"], jax.nn.silu(_rms(x, p["norm2"]["gamma"])), s)
    return x + h


def _attention(cfg, p, x):
    """Single-head spatial self-attention within each frame."""
    B, T, H, W, C = x.shape
    qkv = _conv(cfg, p["to_qkv"], _rms(x, p["norm"]["gamma"])).reshape(B * T, H * W, 3 * C)
    q, k, v = jnp.split(qkv, 3, axis=-1)
    s = jnp.einsum("nqc,nkc->nqk", q, k, precision=_prec(cfg), preferred_element_type=jnp.float32)
    a = jax.nn.softmax(s / math.sqrt(C), axis=-1).astype(v.dtype)
    o = jnp.einsum("nqk,nkc->nqc", a, v, precision=_prec(cfg)).reshape(B, T, H, W, C)
    return _conv(cfg, p["proj"], o) + x


def _resample(cfg, p, x, s: _Stream, mode: str):
    B, T, H, W, C = x.shape
    if mode == "upsample3d":
        if s.first:  # diffusers' "Rep": the first chunk skips the time conv; the next one sees zeros before it
            s.put(jnp.zeros((B, 2, H, W, C), x.dtype))
        else:
            prev = s.take()
            xc = jnp.concatenate([prev.astype(x.dtype), x], axis=1)
            s.put(xc[:, -2:])
            y = _conv(cfg, p["time_conv"], xc)  # [B, T, H, W, 2C]: channel halves are frames 2t, 2t+1
            x = jnp.moveaxis(y.reshape(B, T, H, W, 2, C), 4, 2).reshape(B, 2 * T, H, W, C)
    if mode.startswith("upsample"):
        x = jnp.repeat(jnp.repeat(x, 2, axis=2), 2, axis=3)  # nearest(-exact) x2
        x = _conv(cfg, p["resample"]["1"], x, pad_hw=((1, 1), (1, 1)))
    else:
        x = _conv(cfg, p["resample"]["1"], x, stride=(1, 2, 2), pad_hw=((0, 1), (0, 1)))  # ZeroPad2d(0,1,0,1)
    if mode == "downsample3d":
        if s.first:  # the first chunk passes through; its last frame is cached
            s.put(x[:, -1:])
        else:
            prev = s.take()
            s.put(x[:, -1:])
            x = _conv(cfg, p["time_conv"], jnp.concatenate([prev.astype(x.dtype), x], axis=1), stride=(2, 1, 1))
    return x


def _avg_down(x, cout, ft, fs):
    """AvgDown3D: space/time-to-depth (zero-padding time at the front to a multiple of ft), then average
    consecutive channel groups down to ``cout``."""
    B, T, H, W, C = x.shape
    pad = (ft - T % ft) % ft
    if pad:
        x = jnp.pad(x, ((0, 0), (pad, 0), (0, 0), (0, 0), (0, 0)))
        T += pad
    x = x.reshape(B, T // ft, ft, H // fs, fs, W // fs, fs, C)
    x = x.transpose(0, 1, 3, 5, 7, 2, 4, 6).reshape(B, T // ft, H // fs, W // fs, C * ft * fs * fs)
    return x.reshape(x.shape[:-1] + (cout, -1)).mean(axis=-1)


def _dup_up(x, cout, ft, fs, first):
    """DupUp3D: repeat channels, depth-to-space/time; the first chunk keeps only the last of its ft frames."""
    B, T, H, W, C = x.shape
    reps = cout * ft * fs * fs // C
    x = jnp.repeat(x, reps, axis=-1).reshape(B, T, H, W, cout, ft, fs, fs)
    x = x.transpose(0, 1, 5, 2, 6, 3, 7, 4).reshape(B, T * ft, H * fs, W * fs, cout)
    return x[:, ft - 1:] if first else x


def _mid(cfg, p, x, s):
    x = _resblock(cfg, p["resnets"]["0"], x, s)
    x = _attention(cfg, p["attentions"]["0"], x)
    return _resblock(cfg, p["resnets"]["1"], x, s)


def _encoder_chunk(cfg: WanVAEConfig, p, x, cache, first: bool):
    s = _Stream(cache, first)
    x = _causal_conv(cfg, p["conv_in"], x, s)
    _, blocks = encoder_layout(cfg)
    for k, b in enumerate(blocks):
        bp = p["down_blocks"][str(k)]
        if b[0] == "res":
            x = _resblock(cfg, bp, x, s)
        elif b[0] == "attn":
            x = _attention(cfg, bp, x)
        elif b[0] == "resample":
            x = _resample(cfg, bp, x, s, b[2])
        else:
            _, _cin, cout, temporal, flag = b
            shortcut = _avg_down(x, cout, 2 if temporal else 1, 2 if flag else 1)
            for j in range(cfg.num_res_blocks):
                x = _resblock(cfg, bp["resnets"][str(j)], x, s)
            if flag:
                x = _resample(cfg, bp["downsampler"], x, s, "downsample3d" if temporal else "downsample2d")
            x = x + shortcut
    x = _mid(cfg, p["mid_block"], x, s)
    x = _causal_conv(cfg, p["conv_out"], jax.nn.silu(_rms(x, p["norm_out"]["gamma"])), s)
    return x, s.new


def _decoder_chunk(cfg: WanVAEConfig, p, x, cache, first: bool):
    s = _Stream(cache, first)
    x = _causal_conv(cfg, p["conv_in"], x, s)
    x = _mid(cfg, p["mid_block"], x, s)
    _, blocks = decoder_layout(cfg)
    for k, b in enumerate(blocks):
        bp = p["up_blocks"][str(k)]
        x0 = x
        for j in range(cfg.num_res_blocks + 1):
            x = _resblock(cfg, bp["resnets"][str(j)], x, s)
        if b[0] == "up":
            if b[3] is not None:
                x = _resample(cfg, bp["upsamplers"]["0"], x, s, b[3])
        elif b[4]:
            _, _cin, cout, temporal, _ = b
            x = _resample(cfg, bp["upsampler"], x, s, "upsample3d" if temporal else "upsample2d")
            x = x + _dup_up(x0, cout, 2 if temporal else 1, 2, first)
    x = _causal_conv(cfg, p["conv_out"], jax.nn.silu(_rms(x, p["norm_out"]["gamma"])), s)
    return x, s.new


def _stream(cfg, chunk_fn, p, first_chunk, rest):
    """Run ``chunk_fn`` on the first chunk, then ``lax.scan`` it over ``rest`` ([n, B, t, ...]) carrying the
    temporal caches; outputs concatenated along time."""
    fn = jax.checkpoint(chunk_fn, static_argnums=(0, 4)) if cfg.remat else chunk_fn
    out0, cache = fn(cfg, p, first_chunk, None, True)
    if rest.shape[0] == 0:
        return out0

    def body(c, xc):
        out, c = fn(cfg, p, xc, c, False)
        return c, out

    _, outs = lax.scan(body, cache, rest)  # [n, B, t', ...]
    outs = jnp.moveaxis(outs, 0, 1)
    outs = outs.reshape((outs.shape[0], -1) + outs.shape[3:])
    return jnp.concatenate([out0, outs], axis=1)


# ----------------------------------------------------------------------------------------------------------------
# Public pure functions
# ----------------------------------------------------------------------------------------------------------------
def patchify(x, p):
    """diffusers ``patchify`` in channels-last: [B, T, H, W, C] -> [B, T, H/p, W/p, C*p*p], channel
    c*p*p + pw*p + ph (note: the width offset is the slower one)."""
    if not p or p == 1:
        return x
    B, T, H, W, C = x.shape
    if H % p or W % p:
        raise ValueError(f"height {H} and width {W} must be multiples of patch_size {p}")
    x = x.reshape(B, T, H // p, p, W // p, p, C).transpose(0, 1, 2, 4, 6, 5, 3)
    return x.reshape(B, T, H // p, W // p, C * p * p)


def unpatchify(x, p):
    if not p or p == 1:
        return x
    B, T, H, W, Cp = x.shape
    x = x.reshape(B, T, H, W, Cp // (p * p), p, p).transpose(0, 1, 2, 6, 3, 5, 4)
    return x.reshape(B, T, H * p, W * p, Cp // (p * p))


def encode_moments(params, cfg: WanVAEConfig, video: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Float video [B, T, H, W, C] in [-1, 1] -> posterior (mean, logvar), each [B, 1 + (T-1)//4, h, w, z_dim].
    ``mean`` is diffusers' ``latent_dist.mode()`` (raw, unnormalised latents)."""
    x = video.astype(jnp.dtype(cfg.dtype))
    B, T = x.shape[:2]
    n = (T - 1) // CHUNK
    x = patchify(x[:, :1 + CHUNK * n], cfg.patch_size)
    rest = jnp.moveaxis(x[:, 1:].reshape((B, n, CHUNK) + x.shape[2:]), 1, 0)
    out = _stream(cfg, _encoder_chunk, params["encoder"], x[:, :1], rest)
    h = _conv(cfg, params["quant_conv"], out)
    mean, logvar = jnp.split(h, 2, axis=-1)
    return mean, jnp.clip(logvar, -30.0, 20.0)


def encode(params, cfg: WanVAEConfig, video: jax.Array, key: jax.Array | None = None) -> jax.Array:
    """Raw latents: the posterior mean, or a sample from it when ``key`` is given."""
    mean, logvar = encode_moments(params, cfg, video)
    if key is None:
        return mean
    return mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, mean.shape, mean.dtype)


def decode(params, cfg: WanVAEConfig, z: jax.Array, clamp: bool = True) -> jax.Array:
    """Raw latents [B, t, h, w, z_dim] -> video [B, 1 + 4 (t-1), H, W, C], clamped to [-1, 1] like diffusers
    (``clamp=False`` keeps gradients flowing for out-of-range pixels when training)."""
    x = _conv(cfg, params["post_quant_conv"], z.astype(jnp.dtype(cfg.dtype)))
    rest = jnp.moveaxis(x[:, 1:], 1, 0)[:, :, None]  # one latent frame per chunk
    out = unpatchify(_stream(cfg, _decoder_chunk, params["decoder"], x[:, :1], rest), cfg.patch_size)
    return jnp.clip(out, -1.0, 1.0) if clamp else out


def kl_divergence(mean, logvar):
    """KL(posterior || N(0, 1)) summed over latent elements, per batch item (diffusers' ``kl()``)."""
    return 0.5 * jnp.sum(mean ** 2 + jnp.exp(logvar) - 1.0 - logvar, axis=tuple(range(1, mean.ndim)))


def _stats(cfg, dtype):
    mean = jnp.asarray(cfg.latents_mean if cfg.latents_mean is not None else (0.0,) * cfg.z_dim, dtype)
    inv_std = 1.0 / jnp.asarray(cfg.latents_std if cfg.latents_std is not None else (1.0,) * cfg.z_dim, dtype)
    return mean, inv_std


def normalize_latents(cfg: WanVAEConfig, z):
    """(z - latents_mean) * (1 / latents_std), as the Wan / Cosmos pipelines do."""
    mean, inv_std = _stats(cfg, z.dtype)
    return (z - mean) * inv_std


def denormalize_latents(cfg: WanVAEConfig, z):
    mean, inv_std = _stats(cfg, z.dtype)
    return z / inv_std + mean


# ----------------------------------------------------------------------------------------------------------------
# Tokenizer
# ----------------------------------------------------------------------------------------------------------------
def _to_unit(frames):
    return frames.astype(jnp.float32) / 127.5 - 1.0 if frames.dtype == jnp.uint8 else frames


def latents_to_tokens(z, p):
    """[..., h, w, c] -> [..., rows * cols, p*p*c]: zero-pad h, w to multiples of p, patches in (row, col)
    order with features (pi, pj, c) -- the pixel tokenizer's order."""
    *lead, h, w, c = z.shape
    rows, cols = -(-h // p), -(-w // p)
    if rows * p != h or cols * p != w:
        z = jnp.pad(z, [(0, 0)] * len(lead) + [(0, rows * p - h), (0, cols * p - w), (0, 0)])
    z = jnp.moveaxis(z.reshape(*lead, rows, p, cols, p, c), -4, -3)
    return z.reshape(*lead, rows * cols, p * p * c)


def tokens_to_latents(tokens, p, latent_hw):
    h, w = latent_hw
    rows, cols = -(-h // p), -(-w // p)
    *lead, _n, d = tokens.shape
    c = d // (p * p)
    z = jnp.moveaxis(tokens.reshape(*lead, rows, cols, p, p, c), -3, -4).reshape(*lead, rows * p, cols * p, c)
    return z[..., :h, :w, :]


# The heavy parts, jitted once per (config, shape): the tokenizer's eager calls and direct calls share them.
encode_moments_jit = jax.jit(encode_moments, static_argnums=1)
decode_jit = jax.jit(decode, static_argnums=(1, 3))


def _batched(fn, x, batch_size):
    """fn over the leading axis in slices of ``batch_size`` (bounded memory for many videos): a Python loop over
    equal-shaped slices (one compile) when eager, ``lax.map`` when traced."""
    n = x.shape[0]
    if batch_size is None or n <= batch_size:
        return fn(x)
    if isinstance(x, jax.core.Tracer):
        return lax.map(lambda xi: fn(xi[None])[0], x, batch_size=batch_size)
    pad = -n % batch_size
    xp = jnp.concatenate([x, jnp.zeros((pad,) + x.shape[1:], x.dtype)]) if pad else x
    outs = [fn(xp[i:i + batch_size]) for i in range(0, n + pad, batch_size)]
    return jnp.concatenate(outs)[:n]


def encode_tokens(params, cfg: WanVAEConfig, frames, patch: int = 1, batch_size: int | None = None):
    """uint8 (or [-1, 1] float) frames [..., F, H, W, C] -> normalised-latent tokens [..., f, P, p*p*z_dim]
    (posterior mean)."""
    *lead, F, H, W, C = frames.shape
    x = _to_unit(frames).reshape((-1, F, H, W, C))
    z = _batched(lambda v: encode_moments_jit(params, cfg, v)[0], x, batch_size)
    tok = latents_to_tokens(normalize_latents(cfg, z), patch)
    return tok.reshape(*lead, *tok.shape[1:])


def decode_tokens(params, cfg: WanVAEConfig, tokens, image_size, patch: int = 1, batch_size: int | None = None,
                  clamp: bool = True):
    """Tokens [..., f, P, D] -> float video [..., 1 + 4 (f-1), H, W, C] in [-1, 1]."""
    H, W = image_size
    r = cfg.spatial_ratio
    *lead, f, n, d = tokens.shape
    z = denormalize_latents(cfg, tokens_to_latents(tokens.reshape((-1, f, n, d)), patch, (H // r, W // r)))
    x = _batched(lambda v: decode_jit(params, cfg, v, clamp), z, batch_size)
    return x.reshape(*lead, *x.shape[1:])
