"""Compiled train-step temp memory of dense vs blockwise attention at ~2k / 4k / 8k tokens per sample, next to
``memory.activation_estimate`` (small width, one sample, this machine's first device; nothing is run, only compiled).

    python bench/attention_memory.py [--impls dense:none blockwise:none blockwise:dots blockwise:block]

The ``tiny`` config at patch 4 (3 views x 6 frames of 32x56 / 56x64 / 64x112 pixels: 2,020 / 4,036 / 8,068
tokens), dim 128, 4 layers. Prints a markdown table (measured = ``memory_analysis().temp_size_in_bytes``) and,
last, ``attention_memory: growth_dense=<x> growth_blockwise=<y>``: the measured factor per doubling of the
sequence (4 = quadratic, 2 = linear), geometric mean over the two doublings, remat "none".

``--kernel`` instead compares the blockwise kernel's backward alone (2 heads, head_dim 32, 512-token tiles) with
its custom_vjp (flash backward) and with plain autodiff through its scans, at 2,048 and 4,096 tokens."""
from __future__ import annotations

import argparse
import math

from sc3_jax.train import memory
from sc3_jax.core.config import MeshConfig, load_config, replace
from sc3_jax.model import tokenizer

SIZES = {2020: (32, 56), 4036: (56, 64), 8068: (64, 112)}


def config(image, impl: str, remat: str):
    return replace(load_config("tiny"), data=dict(image_size=tuple(image), batch_size=1),
                   model=dict(patch_size=4, action_reads_frames=False, attention_impl=impl, remat=remat))


def kernel_backward():
    import jax
    import jax.numpy as jnp

    from sc3_jax.model import attention

    def temp(f, *a):
        return jax.jit(jax.grad(f, argnums=(0, 1, 2))).lower(*a).compile().memory_analysis().temp_size_in_bytes

    for n in (2048, 4096):
        q, k = jnp.ones((1, 2, 2, n, 32)), jnp.ones((1, 2, n, 32))
        args = (None, None, False, 0, n, 512, 512)
        custom = temp(lambda q, k, v: jnp.sum(attention._flash(q, k, v, *args)[0] ** 2), q, k, k)
        plain = temp(lambda q, k, v: jnp.sum(attention._flash_fwd(q, k, v, *args)[0][0] ** 2), q, k, k)
        print(f"{n} tokens: backward temp custom_vjp {custom / 1e6:.0f} MB, plain autodiff {plain / 1e6:.0f} MB")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--impls", nargs="+", default=["dense:none", "blockwise:none", "blockwise:dots",
                                                   "blockwise:block", "dense:block"])
    ap.add_argument("--kernel", action="store_true", help="the kernel's backward: custom_vjp vs plain autodiff")
    args = ap.parse_args(argv)
    if args.kernel:
        kernel_backward()
        return 0
    mesh = MeshConfig(1, 1, 1, 1)
    measured = {}
    print("| tokens | attention | remat | compiled temp | estimate | compiled / estimate |\n|---|---|---|---|---|---|")
    for n, image in SIZES.items():
        for spec in args.impls:
            impl, remat = spec.split(":")
            cfg = config(image, impl, remat)
            assert tokenizer.tokens_per_sample(cfg) == n
            m = memory.compiled_memory(cfg, mesh).temp_size_in_bytes
            e = memory.activation_estimate(cfg, mesh)
            measured[n, impl, remat] = m
            print(f"| {n:,} | {impl} | {remat} | {m / 1e6:,.0f} MB | {e / 1e6:,.0f} MB | {m / e:.2f} |", flush=True)
    growth = {}
    for impl in ("dense", "blockwise"):
        r = [measured.get((b, impl, "none"), math.nan) / measured.get((a, impl, "none"), math.nan)
             for a, b in ((2020, 4036), (4036, 8068))]
        growth[impl] = math.sqrt(r[0] * r[1])
    print(f"attention_memory: growth_dense={growth['dense']:.2f} growth_blockwise={growth['blockwise']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
