"""``sc3 convert --from diffusers DIR --to OUT | --from sc3 RUN --to DIR``: Cosmos3 transformer weights between
diffusers and sc3_jax (sc3_jax/commands/convert_cli.py; docs/cosmos3.md)."""
from __future__ import annotations

import dataclasses
from typing import Annotated, Literal

import tyro

from sc3_jax.commands import parse
from sc3_jax.core.errors import UserError

SUMMARY = "Cosmos3 transformer weights between diffusers and sc3_jax"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args:
    """Convert Cosmos3 transformer weights: a diffusers Cosmos3OmniTransformer directory into our params checkpoint
    (`--from diffusers`), or one of our models back into a diffusers directory (`--from sc3`). Every key and shape is
    checked; nothing is written unless the whole conversion succeeds."""

    src_kind: Annotated[Literal["diffusers", "sc3"], tyro.conf.arg(name="from")]
    """the source's format: diffusers (a Cosmos3OmniTransformer directory) or sc3 (a `sc3 train` workdir, an
    exported world model or a `sc3 convert` output)"""
    src: tyro.conf.Positional[str]
    """source directory"""
    to: str
    """output directory (must not exist, or be empty)"""
    dtype: Literal["float32", "bfloat16", "float16"] = "float32"
    """storage dtype of the written weights"""


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "convert")
    from sc3_jax.commands import convert_cli

    try:
        if a.src_kind == "diffusers":
            w = convert_cli.from_diffusers(a.src, a.to, a.dtype)
            use = f"fine-tune from it: sc3 train --config NAME --train.init-from {w.out}; export back: sc3 convert " \
                  f"--from sc3 {w.out} --to DIR"
        else:
            w = convert_cli.to_diffusers(a.src, a.to, a.dtype)
            use = f"load it in PyTorch: Cosmos3OmniTransformer.from_pretrained({str(w.out)!r})"
    except ModuleNotFoundError as e:  # safetensors is an optional dependency
        raise UserError(f"{e}: install the interop extras (pip install -e '.[interop]')") from e
    print(f"wrote {w.out} ({', '.join(w.files)}): {w.params / 1e6:.2f}M parameters as {w.dtype}, from {a.src_kind} "
          f"{a.src}")
    print(use)
    return 0
