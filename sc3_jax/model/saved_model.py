"""The door of a saved world model: config.json, tokenizer/ae.json and norm_stats.json checked field by field --
type, sign, range, and how they fit together (the image size against the tokenizer's) -- before anything is built
from them. A damaged field was a 50-line TypeError from inside JAX (``model.dim -192``, ``latent_channels
"sixteen"``) or a ValueError from the tokenizer; here it is one ``UserError`` line naming the file and the field.
Free of JAX: ``checkpoint.read_config`` (every command that reads a model) and the tokenizer loader call it."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from sc3_jax.core.errors import UserError
from sc3_jax.core.validate import check_config_types, is_finite_number

FIX = "restore it from a copy, or export the model again"
AE_FIX = "restore it from a copy, or train the tokenizer again (`sc3 train-tokenizer`)"

# config.json's numeric fields whose sign and size the model's arrays depend on: (section, field) -> (low, high,
# what). A tuple field's every entry; None (unset) passes. The highs are far past any model, below what would
# overflow a shape.
CONFIG_BOUNDS = {
    ("model", "dim"): (1, 1 << 16, "channels"), ("model", "depth"): (1, 4096, "layers"),
    ("model", "num_heads"): (1, 4096, "heads"), ("model", "num_kv_heads"): (1, 4096, "heads"),
    ("model", "head_dim"): (2, 1 << 14, "channels"), ("model", "mlp_dim"): (1, 1 << 20, "channels"),
    ("model", "rope_axes_dim"): (0, 1 << 13, "rotary frequencies"), ("model", "rope_theta"): (1e-6, 1e12, "a base"),
    ("model", "time_embed_dim"): (2, 1 << 16, "channels"), ("model", "norm_eps"): (1e-12, 1.0, "an epsilon"),
    ("model", "patch_size"): (1, 1024, "a patch's side"), ("model", "frame_tokens"): (1, 1 << 24, "tokens"),
    ("model", "channels"): (1, 1 << 14, "values per pixel"), ("model", "num_views"): (1, 64, "cameras"),
    ("model", "action_dim"): (1, 4096, "entries of an action"),
    ("model", "num_action_domains"): (1, 1 << 16, "embodiments"), ("model", "attention_block"): (1, 1 << 24, "tokens"),
    ("model", "vocab_size"): (0, 1 << 24, "tokens"), ("model", "base_fps"): (1e-6, 1e6, "frames per second"),
    ("model", "fps"): (1e-6, 1e6, "frames per second"), ("model", "temporal_compression"): (1, 64, "frames"),
    ("model", "mrope_margin"): (0, 1 << 30, "positions"), ("model", "timestep_scale"): (1e-12, 1e6, "a scale"),
    ("data", "fps"): (1e-3, 1000, "the episodes' frame rate"),
    ("data", "state_dim"): (0, 4096, "the robot state's size"),
    ("data", "image_size"): (1, 16384, "pixels a side"), ("data", "context_frames"): (1, 1024, "frames"),
    ("data", "future_frames"): (1, 1024, "frames"), ("data", "strides"): (1, 1000, "a frame stride"),
    ("sample", "steps"): (1, 1000, "sampler steps"), ("sample", "inverse_steps"): (1, 1000, "sampler steps"),
    ("sample", "context_noise"): (0, 1, "a noise level"), ("rollout", "policy_chunk"): (1, 100_000, "actions"),
    ("rollout", "keep_frames"): (1, 1024, "frames"), ("rollout", "control_hz"): (1e-3, 1e4, "frames per second"),
    ("rollout", "policy_hz"): (1e-3, 1e5, "actions per second"),
}


def _show(x) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}"


def check_bounds(obj, bounds: dict, where: str, fix: str, prefix: str = "") -> None:
    """Every field of ``bounds`` ((section, field) -> (low, high, what); section None: ``obj``'s own) a finite
    number within [low, high] (each entry of a tuple), else one line naming the field."""
    for (section, field), (low, high, what) in bounds.items():
        value = getattr(getattr(obj, section) if section else obj, field)
        name = f"{prefix}{section}.{field}" if section else f"{prefix}{field}"
        for v in value if isinstance(value, (tuple, list)) else (value,):
            if v is not None and not (is_finite_number(v) and low <= v <= high):
                raise UserError(f"{where}: {name} is {value!r}, expected {what}, a number from {_show(low)} to "
                                f"{_show(high)}; {fix}")


def check_options(cfg) -> None:
    """A config to train (``sc3 train --config``: a named config, a .py file or a run's config.json, and the
    ``--SECTION.FIELD`` overrides) within ``CONFIG_BOUNDS``, each field named as its option (``--model.dim -192``
    was a JAX TypeError)."""
    from sc3_jax.core.validate import in_range

    for (section, field), (low, high, what) in CONFIG_BOUNDS.items():
        value = getattr(getattr(cfg, section), field)
        for v in value if isinstance(value, tuple) else (value,):
            if v is not None:
                in_range(f"--{section}.{field.replace('_', '-')}", v, low, high, what)


def check_config(cfg, where: str, fix: str = FIX) -> None:
    """A saved model's config (``where``: its config.json) at the door: every field's type
    (``validate.check_config_types``), the sign and range of every numeric field its arrays depend on
    (``CONFIG_BOUNDS``), its views each named once (their count against model.num_views is the data's check:
    ``data/shape.py``; a `sc3 convert` output records one view of Cosmos3's), and its image size a whole number of
    pixel patches."""
    from sc3_jax.core.config import Config

    check_config_types(cfg, Config(), where, fix)
    check_bounds(cfg, CONFIG_BOUNDS, where, fix)
    names = list(cfg.data.views)
    if not names:
        raise UserError(f"{where}: data.views is [], expected the model's cameras, in its view order; {fix}")
    twice = sorted({v for v in names if names.count(v) > 1}, key=names.index)
    if twice:  # each camera is fed in at its view's position: a name twice would feed one camera in as another
        raise UserError(f"{where}: data.views {names} names {', '.join(map(repr, twice))} twice; each view is one "
                        f"camera, in the model's view order: {fix}")
    p, size = cfg.model.patch_size, list(cfg.data.image_size)
    if cfg.model.tokenizer == "pixel" and any(s % p for s in size):
        raise UserError(f"{where}: data.image_size {size} is not a multiple of model.patch_size {p} (the pixel "
                        f"tokenizer's patches); {fix}")


def check_tokenizer(cfg, where: str) -> None:
    """A conv_ae model's tokenizer (``cfg.model.tokenizer_path``, resolved) read at the door (:func:`read_ae`), and
    config.json's image size against the one it was trained on and its patches (``where``: config.json)."""
    d = Path(cfg.model.tokenizer_path or "")
    if cfg.model.tokenizer != "conv_ae" or not cfg.model.tokenizer_path or not (d / "ae.json").exists():
        return  # none to read: a command that needs it says so where it loads it (the config alone may do)
    ae_cfg, trained = read_ae(d)
    size = tuple(cfg.data.image_size)
    if size != trained:
        raise UserError(f"{where}: data.image_size {list(size)}, its tokenizer ({d / 'ae.json'}) was trained on "
                        f"{list(trained)} images; {FIX}")
    cells = ae_cfg.downsample * cfg.model.patch_size
    if any(s % cells for s in size):
        raise UserError(f"{where}: data.image_size {list(size)} is not a multiple of the tokenizer's downsample "
                        f"{ae_cfg.downsample} x model.patch_size {cfg.model.patch_size}; {FIX}")


AE_BOUNDS = {(None, "latent_channels"): (1, 4096, "channels"), (None, "downsample"): (2, 256, "pixels a side"),
             (None, "width"): (1, 1 << 14, "channels"), (None, "mid_width"): (1, 1 << 14, "channels"),
             (None, "out_width"): (1, 1 << 14, "channels"), (None, "blocks"): (0, 256, "residual blocks")}


def read_ae(directory: str | Path):
    """(AEConfig, (H, W)) of a learned tokenizer's ae.json, every field checked (an integer, its sign and range,
    downsample a power of two, image_size two sides it divides), else one line naming ae.json and the field."""
    from sc3_jax.core import atomic
    from sc3_jax.core.tokenizer_config import AEConfig

    path = Path(directory) / "ae.json"
    meta = atomic.read_json(path, AE_FIX)
    if not isinstance(meta, dict) or not isinstance(meta.get("config"), dict):
        raise UserError(f"{path}: expected an object with \"config\" (the autoencoder's fields) and \"image_size\"; "
                        f"{AE_FIX}")
    fields = {f.name for f in dataclasses.fields(AEConfig)}
    raw = meta["config"]
    for name in sorted(fields | set(raw)):
        if name not in raw or name not in fields:
            what = "missing" if name not in raw else "not a field of the autoencoder"
            raise UserError(f"{path}: config.{name} is {what}; {AE_FIX}")
        v = raw[name]
        if not isinstance(v, int) or isinstance(v, bool):
            raise UserError(f"{path}: config.{name} is {json.dumps(v)}, expected an integer; {AE_FIX}")
    cfg = AEConfig.__new__(AEConfig)  # fields set without __post_init__: its check is ours, in ae.json's words
    for name in fields:
        object.__setattr__(cfg, name, raw[name])
    check_bounds(cfg, AE_BOUNDS, str(path), AE_FIX, "config.")
    if cfg.downsample & (cfg.downsample - 1):
        raise UserError(f"{path}: config.downsample is {cfg.downsample}, expected a power of two; {AE_FIX}")
    size = meta.get("image_size")
    if not (isinstance(size, list) and len(size) == 2 and all(
            isinstance(s, int) and not isinstance(s, bool) and 1 <= s <= 16384 and s % cfg.downsample == 0
            for s in size)):
        raise UserError(f"{path}: image_size is {json.dumps(size)}, expected [H, W], two pixel counts that "
                        f"config.downsample {cfg.downsample} divides; {AE_FIX}")
    return AEConfig(**raw), tuple(size)


def check_norm_stats(path: Path, cfg) -> None:
    """A saved model's norm_stats.json (where it has one) read at the door (``NormStats.load``: every field), its
    action dimension the model's."""
    f = Path(path) / "norm_stats.json"
    if not f.exists():
        return  # a `sc3 convert` output: none (the commands that need one say so)
    from sc3_jax.data.norm_stats import NormStats

    dim = NormStats.load(f).mean.shape[0]
    if dim != cfg.model.action_dim:
        raise UserError(f"{f}: mean has {dim} entries, config.json model.action_dim is {cfg.model.action_dim}: the "
                        f"statistics of another model; {FIX}")

