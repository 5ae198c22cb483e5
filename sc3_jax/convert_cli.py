"""``sc3 convert``: Cosmos3 transformer weights between diffusers and sc3_jax.

    sc3 convert --from diffusers DIR --to OUT     diffusers Cosmos3OmniTransformer dir -> OUT/config.json + OUT/params
                                                  (an orbax checkpoint of the params), which `sc3 train
                                                  --train.init-from OUT` and `sc3 rollout` read
    sc3 convert --from sc3 RUN --to DIR           a `sc3 train` workdir / exported model / convert output ->
                                                  config.json + diffusion_pytorch_model.safetensors for PyTorch users

Every key and shape is checked both ways (model/convert.py); nothing is written unless the whole conversion
succeeded, so a failed run never leaves a half-written OUT.
"""
from __future__ import annotations

import argparse
import dataclasses
import shutil
import tempfile
from pathlib import Path


DTYPES = ("float32", "bfloat16", "float16")


def from_diffusers(src: str, out: str, dtype: str = "float32") -> Path:
    from sc3_jax import checkpoint
    from sc3_jax.config import Config
    from sc3_jax.model import convert
    mcfg, params = convert.load_diffusers(src, dtype=dtype)
    cfg = Config(model=dataclasses.replace(mcfg, param_dtype=dtype))
    return _write_atomically(out, lambda tmp: checkpoint.save_converted(tmp, cfg, params))


def to_diffusers(src: str, out: str, dtype: str = "float32") -> Path:
    import jax.numpy as jnp

    from sc3_jax import checkpoint
    from sc3_jax.model import convert
    cfg = checkpoint.read_config(src)
    params = checkpoint.load_params(src, cfg)
    return _write_atomically(out, lambda tmp: convert.save_diffusers(cfg.model, params, str(tmp),
                                                                     dtype=jnp.dtype(dtype)))


def _write_atomically(out: str, write) -> Path:
    out_p = Path(out)
    if out_p.exists() and any(out_p.iterdir()):
        raise FileExistsError(f"{out}: exists and is not empty (choose a new --to)")
    tmp = Path(tempfile.mkdtemp(prefix=".convert-", dir=out_p.parent if out_p.parent.exists() else None))
    try:
        write(tmp)
        if out_p.exists():
            out_p.rmdir()
        shutil.move(str(tmp), str(out_p))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_p


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="sc3 convert", description=__doc__.split("\n\n")[0])
    ap.add_argument("--from", dest="src_kind", required=True, choices=("diffusers", "sc3"))
    ap.add_argument("src", help="source directory")
    ap.add_argument("--to", required=True, help="output directory (must not exist or be empty)")
    ap.add_argument("--dtype", default="float32", choices=DTYPES)
    a = ap.parse_args(argv)
    fn = from_diffusers if a.src_kind == "diffusers" else to_diffusers
    print(f"wrote {fn(a.src, a.to, a.dtype)}")
    return 0
