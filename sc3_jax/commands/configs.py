"""``sc3 configs``: the named configs with their parameter counts."""
from __future__ import annotations

import dataclasses

from sc3_jax.commands import parse

SUMMARY = "the named configs with their parameter counts"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args:
    """Each named config with its parameter count (from abstract shapes: nothing is allocated)."""


def main(argv: list[str]) -> int:
    parse(Args, argv, "configs")  # no options; --help, and a stray argument is an error
    from sc3_jax.model import checkpoint
    from sc3_jax.core.config import available_configs, load_config
    from sc3_jax.model import dit
    from sc3_jax.model.tokenizer import tokens_per_sample
    from sc3_jax.train.plan_vae import shape_only_vae

    print("named configs (sc3_jax/configs; --config NAME, or --config PATH to a file of your own):")
    for name in available_configs():
        cfg = load_config(name)
        try:  # a config whose tokenizer weights are missing here is listed, not fatal
            with shape_only_vae(cfg):  # a Wan VAE (0.1-0.7B parameters) is never built just to be sized
                n = dit.count_params(checkpoint.param_shapes(cfg))
                tokens = tokens_per_sample(cfg)
        except (FileNotFoundError, ValueError) as e:
            print(f"  {name:24s} (not sized here: {e})")
            continue
        print(f"  {name:24s} {n / 1e6:10.2f}M params  {tokens:6d} tokens/sample  batch {cfg.data.batch_size}")
    return 0
