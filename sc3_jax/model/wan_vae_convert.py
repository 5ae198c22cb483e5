"""diffusers ``AutoencoderKLWan`` checkpoints (config.json + safetensors) <-> ``wan_vae`` config and params.

No torch at run time: tensors are read/written with ``safetensors.numpy`` (bfloat16 / float8 files, which numpy
cannot name, are read by a small header parser through ``ml_dtypes``). Every key and shape is checked against
``wan_vae.param_specs``; a mismatch raises one error listing all missing, unexpected and mis-shaped keys.

    cfg, params = load_diffusers("path/to/vae")           # directory with config.json + *.safetensors
    save_diffusers(cfg, params, "out/vae")                # AutoencoderKLWan.from_pretrained("out/vae") loads it
"""
from __future__ import annotations

import json
import os
import struct

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.core import atomic
from sc3_jax.model.shapes import check_shapes
from sc3_jax.model.wan_vae import ParamSpec, WanVAEConfig, param_specs

WEIGHTS_NAME = "diffusion_pytorch_model.safetensors"
INDEX_NAME = "diffusion_pytorch_model.safetensors.index.json"
CONFIG_NAME = "config.json"
CLASS_NAME = "AutoencoderKLWan"

# diffusers config key -> WanVAEConfig field
_CONFIG_KEYS = {
    "base_dim": "base_dim", "decoder_base_dim": "decoder_base_dim", "z_dim": "z_dim", "dim_mult": "dim_mult",
    "num_res_blocks": "num_res_blocks", "attn_scales": "attn_scales", "temperal_downsample": "temporal_downsample",
    "dropout": "dropout", "latents_mean": "latents_mean", "latents_std": "latents_std", "is_residual": "is_residual",
    "in_channels": "in_channels", "out_channels": "out_channels", "patch_size": "patch_size",
    "scale_factor_temporal": "scale_factor_temporal", "scale_factor_spatial": "scale_factor_spatial",
}


# ----------------------------------------------------------------------------------------------------------------
# Config
# ----------------------------------------------------------------------------------------------------------------
def config_from_diffusers(d: dict, strict: bool = True, **overrides) -> WanVAEConfig:
    """A diffusers config dict -> WanVAEConfig. Keys starting with "_" (class name, version) are ignored; any
    other unknown key raises when ``strict`` (an architecture option this port would silently ignore)."""
    if d.get("_class_name", CLASS_NAME) != CLASS_NAME:
        raise ValueError(f"config is for {d['_class_name']!r}, not {CLASS_NAME}")
    unknown = sorted(k for k in d if not k.startswith("_") and k not in _CONFIG_KEYS)
    if unknown and strict:
        raise ValueError(f"unknown AutoencoderKLWan config keys {unknown} (pass strict=False to ignore)")
    kw = {_CONFIG_KEYS[k]: v for k, v in d.items() if k in _CONFIG_KEYS}
    kw.update(overrides)
    return WanVAEConfig(**kw)


def config_to_diffusers(cfg: WanVAEConfig) -> dict:
    out = {"_class_name": CLASS_NAME}
    for k, field in _CONFIG_KEYS.items():
        v = getattr(cfg, field)
        out[k] = list(v) if isinstance(v, tuple) else v
    return out


# ----------------------------------------------------------------------------------------------------------------
# State dicts
# ----------------------------------------------------------------------------------------------------------------
def flat_specs(cfg: WanVAEConfig) -> dict[str, ParamSpec]:
    """{diffusers key: spec} for every parameter of this config."""
    out = {}

    def walk(tree, prefix):
        for k, v in tree.items():
            key = f"{prefix}.{k}" if prefix else k
            if isinstance(v, ParamSpec):
                out[key] = v
            else:
                walk(v, key)

    walk(param_specs(cfg), "")
    return out


def _to_ours(spec: ParamSpec, a: np.ndarray) -> np.ndarray:
    if spec.kind == "conv":  # [O, I, *k] -> [*k, I, O]
        return np.transpose(a, tuple(range(2, a.ndim)) + (1, 0))
    if spec.kind == "gamma":
        return a.reshape(spec.shape)
    return a


def _to_torch(spec: ParamSpec, a: np.ndarray) -> np.ndarray:
    if spec.kind == "conv":  # [*k, I, O] -> [O, I, *k]
        n = a.ndim
        return np.ascontiguousarray(np.transpose(a, (n - 1, n - 2) + tuple(range(n - 2))))
    if spec.kind == "gamma":
        return a.reshape(spec.torch_shape)
    return a


def params_from_state_dict(cfg: WanVAEConfig, sd: dict[str, np.ndarray], dtype=None) -> dict:
    """diffusers state dict (numpy arrays) -> our params (jnp arrays of ``dtype`` or cfg.param_dtype)."""
    specs = flat_specs(cfg)
    check_shapes({k: s.torch_shape for k, s in specs.items()}, {k: np.shape(v) for k, v in sd.items()},
                 "state dict does not match the AutoencoderKLWan config:")
    dtype = jnp.dtype(dtype or cfg.param_dtype)
    params: dict = {}
    for key, spec in specs.items():
        node = params
        *path, leaf = key.split(".")
        for part in path:
            node = node.setdefault(part, {})
        node[leaf] = jnp.asarray(_to_ours(spec, np.asarray(sd[key])), dtype=dtype)
    return params


def state_dict_from_params(cfg: WanVAEConfig, params: dict, dtype=None) -> dict[str, np.ndarray]:
    """Our params -> diffusers state dict of numpy arrays (in the params' dtype unless ``dtype``)."""
    specs = flat_specs(cfg)
    flat = {}

    def walk(tree, prefix):
        for k, v in tree.items():
            key = f"{prefix}.{k}" if prefix else k
            if isinstance(v, dict):
                walk(v, key)
            else:
                flat[key] = v

    walk(params, "")
    # compared in our layout: a wrong-shaped leaf is reported with its (our-layout) shape
    check_shapes({k: s.shape for k, s in specs.items()}, {k: np.shape(v) for k, v in flat.items()},
                 "params do not match the AutoencoderKLWan config:")
    out = {}
    for k, spec in specs.items():
        a = np.asarray(jax.device_get(flat[k]))
        if dtype is not None:
            a = a.astype(dtype)
        out[k] = _to_torch(spec, a)
    return out


# ----------------------------------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------------------------------
_ST_DTYPES = {"F64": "float64", "F32": "float32", "F16": "float16", "BF16": "bfloat16", "F8_E4M3": "float8_e4m3fn",
              "F8_E5M2": "float8_e5m2", "I64": "int64", "I32": "int32", "I16": "int16", "I8": "int8", "U8": "uint8",
              "BOOL": "bool"}


def _read_safetensors_raw(path: str) -> dict[str, np.ndarray]:
    """Header-parsing reader for dtypes numpy cannot name (bfloat16, float8) via ml_dtypes."""
    import ml_dtypes

    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        header = json.loads(f.read(n))
        data = f.read()
    out = {}
    for k, meta in header.items():
        if k == "__metadata__":
            continue
        begin, end = meta["data_offsets"]
        dt = np.dtype(getattr(ml_dtypes, _ST_DTYPES[meta["dtype"]], None) or _ST_DTYPES[meta["dtype"]])
        out[k] = np.frombuffer(data[begin:end], dtype=dt).reshape(meta["shape"]).copy()
    return out


def read_safetensors(path: str) -> dict[str, np.ndarray]:
    from safetensors.numpy import load_file
    try:
        return load_file(path)
    except TypeError:  # bfloat16 / float8
        return _read_safetensors_raw(path)


def _weight_files(path: str) -> list[str]:
    if os.path.isfile(path):
        return [path]
    index = os.path.join(path, INDEX_NAME)
    if os.path.exists(index):
        with open(index) as f:
            shards = sorted(set(json.load(f)["weight_map"].values()))
        return [os.path.join(path, s) for s in shards]
    single = os.path.join(path, WEIGHTS_NAME)
    if os.path.exists(single):
        return [single]
    found = sorted(f for f in os.listdir(path) if f.endswith(".safetensors"))
    if len(found) == 1:
        return [os.path.join(path, found[0])]
    raise FileNotFoundError(f"no {WEIGHTS_NAME} (or its index) in {path}; safetensors files there: {found}")


def load_diffusers(path: str, config: dict | None = None, dtype=None, strict: bool = True,
                   **cfg_overrides) -> tuple[WanVAEConfig, dict]:
    """A diffusers AutoencoderKLWan directory (or a safetensors file plus ``config``) -> (cfg, params).
    ``cfg_overrides`` set JAX-only options (dtype, precision, remat, ...)."""
    config, sd = read_diffusers_dir(path, config)
    cfg = config_from_diffusers(config, strict=strict, **cfg_overrides)
    return cfg, params_from_state_dict(cfg, sd, dtype)


def read_diffusers_dir(path: str, config: dict | None = None) -> tuple[dict, dict]:
    """(config.json as a dict, state dict of numpy arrays from every safetensors shard) of a diffusers model
    directory (or of one safetensors file plus ``config``)."""
    if config is None:
        cdir = path if os.path.isdir(path) else os.path.dirname(path)
        with open(os.path.join(cdir, CONFIG_NAME)) as f:
            config = json.load(f)
    sd = {}
    for fpath in _weight_files(path):
        for k, v in read_safetensors(fpath).items():
            if k in sd:
                raise ValueError(f"key {k} appears in more than one shard")
            sd[k] = v
    return config, sd


def save_diffusers(cfg: WanVAEConfig, params: dict, path: str, dtype=None, extra_config: dict | None = None):
    """Write ``config.json`` + ``diffusion_pytorch_model.safetensors`` that ``AutoencoderKLWan.from_pretrained``
    loads."""
    return write_diffusers_dir(path, state_dict_from_params(cfg, params, dtype),
                               {**config_to_diffusers(cfg), **(extra_config or {})})


def write_diffusers_dir(path: str, state_dict: dict, conf: dict) -> str:
    """A diffusers model directory: the weights (safetensors), then ``config.json`` -- last, because
    ``from_pretrained`` reads a directory with one as complete."""
    from safetensors.numpy import save_file

    os.makedirs(path, exist_ok=True)
    with atomic.replacing(os.path.join(path, WEIGHTS_NAME)) as tmp:
        save_file(state_dict, str(tmp), metadata={"format": "pt"})
    atomic.write_text(os.path.join(path, CONFIG_NAME), json.dumps(conf, indent=2))
    return path
