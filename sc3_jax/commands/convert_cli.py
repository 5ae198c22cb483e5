"""Cosmos3 transformer weights between diffusers and sc3_jax, written atomically (``sc3 convert`` is
``commands/convert.py``).

    from_diffusers(DIR, OUT)   a diffusers Cosmos3OmniTransformer dir -> OUT/config.json + OUT/params (an orbax
                               checkpoint of the params), which `sc3 train --train.init-from OUT` and `sc3 rollout` read
    to_diffusers(RUN, DIR)     a `sc3 train` workdir / exported model / convert output -> config.json +
                               diffusion_pytorch_model.safetensors for PyTorch users

Every key and shape is checked both ways (model/convert.py); nothing is written unless the whole conversion
succeeded, so a failed run never leaves a half-written OUT.
"""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

from sc3_jax.core import atomic

DTYPES = ("float32", "bfloat16", "float16")


@dataclasses.dataclass(frozen=True)
class Converted:
    """What a conversion wrote: the directory, its top-level entries, the parameter count, the storage dtype."""

    out: Path
    files: tuple[str, ...]
    params: int
    dtype: str


def _count(params) -> int:
    import jax

    return int(sum(x.size for x in jax.tree.leaves(params)))


def from_diffusers(src: str, out: str, dtype: str = "float32") -> Converted:
    from sc3_jax.model import checkpoint
    from sc3_jax.core.config import Config
    from sc3_jax.model import convert
    mcfg, params = convert.load_diffusers(src, dtype=dtype)
    cfg = Config(model=dataclasses.replace(mcfg, param_dtype=dtype))
    return _written(_write_atomically(out, lambda tmp: checkpoint.save_converted(tmp, cfg, params)), params, dtype)


def to_diffusers(src: str, out: str, dtype: str = "float32") -> Converted:
    import jax.numpy as jnp

    from sc3_jax.model import checkpoint
    from sc3_jax.model import convert
    cfg = checkpoint.read_config(src)
    params = checkpoint.load_params(src, cfg)
    path = _write_atomically(out, lambda tmp: convert.save_diffusers(cfg.model, params, str(tmp),
                                                                     dtype=jnp.dtype(dtype)))
    return _written(path, params, dtype)


def _written(out: Path, params, dtype: str) -> Converted:
    return Converted(out, tuple(sorted(p.name + ("/" if p.is_dir() else "") for p in out.iterdir())), _count(params),
                     dtype)


def _write_atomically(out: str, write) -> Path:
    out_p = Path(out)
    if out_p.exists() and any(out_p.iterdir()):
        raise FileExistsError(f"{out}: exists and is not empty (choose a new --to)")
    out_p.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic.temp_dir(out_p)
    try:
        write(tmp)
        if out_p.exists():
            out_p.rmdir()
        shutil.move(str(tmp), str(out_p))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_p
