"""diffusers ``Cosmos3OmniTransformer`` checkpoints (config.json + safetensors) <-> our DiT config and params.

No torch at run time: tensors are read/written with ``safetensors.numpy`` (bfloat16 files through the reader in
``wan_vae_convert``). Every diffusers key maps onto one of our parameters (``dit.param_specs`` of the
Cosmos3-compatible ``ModelConfig``); missing, unexpected and mis-shaped keys raise one error listing them all.

    cfg, params = load_diffusers("path/to/transformer")    # directory with config.json + *.safetensors
    save_diffusers(cfg, params, "out/transformer")         # Cosmos3OmniTransformer.from_pretrained("out/...") loads it

Mapping (per layer i; ours are stacked on a leading layer axis; torch Linear weights are [out, in], ours [in, ...]):
    layers.i.{input_layernorm,post_attention_layernorm}_moe_gen, self_attn.{add_q,add_k,add_v}_proj,
    self_attn.norm_added_{q,k}, self_attn.to_add_out, mlp_moe_gen.*      -> params["layers"] (generation pathway)
    the same names without _moe_gen / add_ (to_q, norm_q, to_out, mlp)   -> params["text_layers"] (understanding)
    norm_moe_gen / norm -> final_norm / text_norm; embed_tokens, lm_head; proj_in/out -> proj_in/out {w, b};
    time_embedder.linear_{1,2} -> time_embed {w1, b1, w2, b2}; action_proj_{in,out}.{fc,bias}.weight ->
    action_{in,out} {w [domains, in, out], b}; action_modality_embed.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.core.config import ModelConfig
from sc3_jax.model import dit
from sc3_jax.model.shapes import check_shapes
from sc3_jax.model.wan_vae_convert import read_diffusers_dir, write_diffusers_dir

WEIGHTS_NAME = "diffusion_pytorch_model.safetensors"
CONFIG_NAME = "config.json"
CLASS_NAME = "Cosmos3OmniTransformer"

# diffusers config key -> ModelConfig field
_CONFIG_KEYS = {
    "hidden_size": "dim", "num_hidden_layers": "depth", "num_attention_heads": "num_heads",
    "num_key_value_heads": "num_kv_heads", "head_dim": "head_dim", "intermediate_size": "mlp_dim",
    "rope_theta": "rope_theta", "rms_norm_eps": "norm_eps", "latent_channel": "channels",
    "latent_patch_size": "patch_size", "action_dim": "action_dim", "num_embodiment_domains": "num_action_domains",
    "base_fps": "base_fps", "enable_fps_modulation": "fps_modulation",
    "unified_3d_mrope_reset_spatial_ids": "reset_spatial_ids",
    "unified_3d_mrope_temporal_modality_margin": "mrope_margin", "timestep_scale": "timestep_scale",
    "vocab_size": "vocab_size",
}
# Architecture options this port does not implement: (key, the only supported value).
_FIXED = {"attention_bias": False, "hidden_act": "silu", "qk_norm_for_text": True, "use_und_k_norm_for_gen": False,
          "sound_gen": False, "action_gen": True}
# Read but with no effect on the weights or the generation forward (dropout is 0 at inference; sound is off).
_IGNORED = {"dtype", "attention_dropout", "sound_dim", "sound_latent_fps", "rope_scaling", "rope_axes_dim",
            "patch_latent_dim"}
# Cosmos3OmniTransformer.__init__ defaults (diffusers 0.42), used for keys a config dict leaves out.
_DEFAULTS = {
    "hidden_size": 4096, "num_hidden_layers": 36, "num_attention_heads": 32, "num_key_value_heads": 8,
    "head_dim": 128, "intermediate_size": 12288, "rope_theta": 5000000.0, "rms_norm_eps": 1e-6,
    "latent_channel": 48, "latent_patch_size": 2, "patch_latent_dim": 192, "action_dim": None,
    "num_embodiment_domains": 32, "base_fps": 24, "enable_fps_modulation": True,
    "unified_3d_mrope_reset_spatial_ids": True, "unified_3d_mrope_temporal_modality_margin": 15000,
    "timestep_scale": 0.001, "vocab_size": 151936, "action_gen": False, "attention_bias": False,
    "hidden_act": "silu", "qk_norm_for_text": True, "use_und_k_norm_for_gen": False, "sound_gen": False,
}
_TOKENIZERS = {48: "wan2.2", 16: "wan2.1"}  # latent channels -> tokenizer (others: tiny test configs, "pixel")


# ----------------------------------------------------------------------------------------------------------------
# Config
# ----------------------------------------------------------------------------------------------------------------
def config_from_diffusers(d: dict, strict: bool = True, **overrides) -> ModelConfig:
    """A Cosmos3OmniTransformer config dict -> a Cosmos3-compatible ModelConfig. ``overrides`` set JAX-only
    options (dtype, remat, context_attention, fps, ...)."""
    if d.get("_class_name", CLASS_NAME) != CLASS_NAME:
        raise ValueError(f"config is for {d['_class_name']!r}, not {CLASS_NAME}")
    d = {**_DEFAULTS, **{k: v for k, v in d.items() if v is not None or k not in _DEFAULTS}}
    bad = [f"{k}={d[k]!r} (supported: {v!r})" for k, v in _FIXED.items() if d[k] != v]
    if bad:
        raise ValueError(f"unsupported {CLASS_NAME} options: {', '.join(bad)}")
    if d["action_dim"] is None:
        raise ValueError("action_gen=True needs action_dim")
    unknown = sorted(k for k in d if not k.startswith("_") and k not in _CONFIG_KEYS and k not in _FIXED
                     and k not in _IGNORED)
    if unknown and strict:
        raise ValueError(f"unknown {CLASS_NAME} config keys {unknown} (pass strict=False to ignore)")
    kw = {_CONFIG_KEYS[k]: v for k, v in d.items() if k in _CONFIG_KEYS}
    sections = d.get("rope_axes_dim")
    if sections is None:
        sections = (d.get("rope_scaling") or {}).get("mrope_section", [24, 20, 20])
    kw["rope_axes_dim"] = tuple(int(s) for s in sections)
    p, c = d["latent_patch_size"], d["latent_channel"]
    if d["patch_latent_dim"] != c * p * p:
        raise ValueError(f"patch_latent_dim {d['patch_latent_dim']} != latent_channel * latent_patch_size^2 = "
                         f"{c * p * p}")
    kw.update(layout="cosmos3", text_pathway=True, view_embedding=False, prediction="velocity", num_views=1,
              time_embed_dim=256, tokenizer=_TOKENIZERS.get(c, "pixel"), anchor_conditioning=False,
              action_to_frames=False, action_reads_frames=False)
    kw.update(overrides)
    return ModelConfig(**kw)


def _check_exportable(cfg: ModelConfig):
    bad = []
    if cfg.layout != "cosmos3" or not cfg.text_pathway:
        bad.append("layout='cosmos3' with text_pathway=True")
    if cfg.view_embedding or cfg.anchor_conditioning or cfg.action_to_frames or cfg.action_reads_frames:
        bad.append("view_embedding and the shortcuts (anchor_conditioning, action_to_frames, action_reads_frames) off")
    if cfg.time_embed_dim != 256:
        bad.append("time_embed_dim=256")
    if cfg.prediction != "velocity":
        bad.append("prediction='velocity'")
    if bad:
        raise ValueError("a Cosmos3OmniTransformer checkpoint needs " + "; ".join(bad))


def config_to_diffusers(cfg: ModelConfig) -> dict:
    _check_exportable(cfg)
    out = {"_class_name": CLASS_NAME}
    for k, field in _CONFIG_KEYS.items():
        out[k] = getattr(cfg, field)
    out.update(_FIXED)
    out.update(rope_axes_dim=list(cfg.rope_axes_dim), patch_latent_dim=token_dim(cfg), attention_dropout=0.0,
               rope_scaling=None, sound_dim=None, sound_latent_fps=25.0)
    return out


def token_dim(cfg: ModelConfig) -> int:
    return cfg.channels * cfg.patch_size ** 2


# ----------------------------------------------------------------------------------------------------------------
# Key mapping
# ----------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Entry:
    path: tuple[str, ...]  # where in our params
    layer: int | None  # index on the leading layer axis of a stacked parameter
    kind: str  # "same", "linear" (torch [out, in] <-> ours [in..., out...]), "domain" ([D, in*out] <-> [D, in, out])
    n_in: int  # "linear": how many of our leading axes are the input
    shape: tuple[int, ...]  # ours (one layer's slice for stacked parameters)

    @property
    def torch_shape(self) -> tuple[int, ...]:
        if self.kind == "linear":
            return (math.prod(self.shape[self.n_in:]), math.prod(self.shape[:self.n_in]))
        if self.kind == "domain":
            return (self.shape[0], math.prod(self.shape[1:]))
        return self.shape


_LAYER = {  # our name -> (generation pathway name, understanding pathway name, kind, n_in)
    "attn_norm": ("input_layernorm_moe_gen", "input_layernorm", "same", 0),
    "wq": ("self_attn.add_q_proj", "self_attn.to_q", "linear", 1),
    "wk": ("self_attn.add_k_proj", "self_attn.to_k", "linear", 1),
    "wv": ("self_attn.add_v_proj", "self_attn.to_v", "linear", 1),
    "q_norm": ("self_attn.norm_added_q", "self_attn.norm_q", "same", 0),
    "k_norm": ("self_attn.norm_added_k", "self_attn.norm_k", "same", 0),
    "wo": ("self_attn.to_add_out", "self_attn.to_out", "linear", 2),
    "mlp_norm": ("post_attention_layernorm_moe_gen", "post_attention_layernorm", "same", 0),
    "w_gate": ("mlp_moe_gen.gate_proj", "mlp.gate_proj", "linear", 1),
    "w_up": ("mlp_moe_gen.up_proj", "mlp.up_proj", "linear", 1),
    "w_down": ("mlp_moe_gen.down_proj", "mlp.down_proj", "linear", 1),
}
_TOP = {  # diffusers key -> (our path, kind, n_in)
    "norm_moe_gen.weight": (("final_norm",), "same", 0),
    "norm.weight": (("text_norm",), "same", 0),
    "embed_tokens.weight": (("embed_tokens",), "same", 0),
    "lm_head.weight": (("lm_head",), "same", 0),
    "proj_in.weight": (("proj_in", "w"), "linear", 1),
    "proj_in.bias": (("proj_in", "b"), "same", 0),
    "proj_out.weight": (("proj_out", "w"), "linear", 1),
    "proj_out.bias": (("proj_out", "b"), "same", 0),
    "time_embedder.linear_1.weight": (("time_embed", "w1"), "linear", 1),
    "time_embedder.linear_1.bias": (("time_embed", "b1"), "same", 0),
    "time_embedder.linear_2.weight": (("time_embed", "w2"), "linear", 1),
    "time_embedder.linear_2.bias": (("time_embed", "b2"), "same", 0),
    "action_proj_in.fc.weight": (("action_in", "w"), "domain", 0),
    "action_proj_in.bias.weight": (("action_in", "b"), "same", 0),
    "action_proj_out.fc.weight": (("action_out", "w"), "domain", 0),
    "action_proj_out.bias.weight": (("action_out", "b"), "same", 0),
    "action_modality_embed": (("action_modality_embed",), "same", 0),
}


def _get(tree, path):
    for p in path:
        tree = tree[p]
    return tree


def key_map(cfg: ModelConfig) -> dict[str, Entry]:
    """{diffusers key: Entry} for every parameter of this (Cosmos3-compatible) config."""
    _check_exportable(cfg)
    specs = dit.param_specs(cfg, token_dim(cfg))
    out = {}
    for key, (path, kind, n_in) in _TOP.items():
        out[key] = Entry(path, None, kind, n_in, _get(specs, path).shape)
    for ours, (gen, und, kind, n_in) in _LAYER.items():
        for stack, name in (("layers", gen), ("text_layers", und)):
            shape = specs[stack][ours].shape[1:]
            for i in range(cfg.depth):
                out[f"layers.{i}.{name}.weight"] = Entry((stack, ours), i, kind, n_in, shape)
    # every one of our parameters is covered exactly once
    covered = {e.path for e in out.values()}
    ours_paths = {tuple(getattr(k, "key", k) for k in kp) for kp, _ in
                  jax.tree_util.tree_flatten_with_path(specs, is_leaf=lambda x: isinstance(x, dit.ParamSpec))[0]}
    if covered != ours_paths:
        raise AssertionError(f"key map out of date: unmapped params {sorted(ours_paths - covered)}")
    return out


def _to_ours(e: Entry, a: np.ndarray) -> np.ndarray:
    if e.kind == "linear":
        return np.ascontiguousarray(a.T).reshape(e.shape)
    return a.reshape(e.shape)


def _to_torch(e: Entry, a: np.ndarray) -> np.ndarray:
    if e.kind == "linear":
        return np.ascontiguousarray(a.reshape(math.prod(e.shape[:e.n_in]), -1).T)
    return np.ascontiguousarray(a.reshape(e.torch_shape))


def params_from_state_dict(cfg: ModelConfig, sd: dict[str, np.ndarray], dtype=None) -> dict:
    """diffusers state dict (numpy arrays) -> our params (jnp arrays of ``dtype`` or cfg.param_dtype)."""
    emap = key_map(cfg)
    check_shapes({k: e.torch_shape for k, e in emap.items()}, {k: np.shape(v) for k, v in sd.items()},
                 f"state dict does not match the {CLASS_NAME} config:")
    dtype = jnp.dtype(dtype or cfg.param_dtype)
    stacked: dict[tuple, list] = {}
    params: dict = {}

    def put(path, value):
        node = params
        for part in path[:-1]:
            node = node.setdefault(part, {})
        node[path[-1]] = jnp.asarray(value, dtype=dtype)

    for key, e in emap.items():
        a = _to_ours(e, np.asarray(sd[key]))
        if e.layer is None:
            put(e.path, a)
        else:
            stacked.setdefault(e.path, [None] * cfg.depth)[e.layer] = a
    for path, arrays in stacked.items():
        put(path, np.stack(arrays))
    return params


def state_dict_from_params(cfg: ModelConfig, params: dict, dtype=None) -> dict[str, np.ndarray]:
    """Our params -> diffusers state dict of numpy arrays (in the params' dtype unless ``dtype``)."""
    emap = key_map(cfg)
    flat = {"/".join(str(getattr(k, "key", k)) for k in kp): v
            for kp, v in jax.tree_util.tree_flatten_with_path(params)[0]}
    expected = {}
    for e in emap.values():
        name = "/".join(e.path)
        expected[name] = ((cfg.depth,) if e.layer is not None else ()) + e.shape
    check_shapes(expected, {k: np.shape(v) for k, v in flat.items()}, f"params do not match the {CLASS_NAME} config:")
    host = {k: np.asarray(jax.device_get(v)) for k, v in flat.items()}
    out = {}
    for key, e in emap.items():
        a = host["/".join(e.path)]
        if e.layer is not None:
            a = a[e.layer]
        if dtype is not None:
            a = a.astype(dtype)
        out[key] = _to_torch(e, a)
    return out


# ----------------------------------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------------------------------
def load_diffusers(path: str, config: dict | None = None, dtype=None, strict: bool = True,
                   **cfg_overrides) -> tuple[ModelConfig, dict]:
    """A diffusers Cosmos3OmniTransformer directory (or a safetensors file plus ``config``) -> (cfg, params).
    A published checkpoint whose keys carry a leading ``model.`` must be re-keyed first (as diffusers' own flat
    layout requires)."""
    config, sd = read_diffusers_dir(path, config)
    cfg = config_from_diffusers(config, strict=strict, **cfg_overrides)
    return cfg, params_from_state_dict(cfg, sd, dtype)


def save_diffusers(cfg: ModelConfig, params: dict, path: str, dtype=None, extra_config: dict | None = None):
    """Write ``config.json`` + ``diffusion_pytorch_model.safetensors`` that
    ``Cosmos3OmniTransformer.from_pretrained`` loads."""
    return write_diffusers_dir(path, state_dict_from_params(cfg, params, dtype),
                               {**config_to_diffusers(cfg), **(extra_config or {})})
