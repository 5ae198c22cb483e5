"""A config sized from its data: a named config carries a token budget per frame (``model.frame_tokens``, every view
together), and the patch size is chosen from the dataset's image size and camera count to meet it, so that a config
name means about the same cost on any robot (``tiny`` on two 96x128 cameras as on three 16x16 ones).

Why the budget is per frame and not per view: a lab adds a camera to see more, not to pay 1.5x per step; the views
share the budget. Why the patch and not the image: the image a lab records is what its policies see, and cutting
it would hide the detail a learned tokenizer is there to keep; a coarser patch keeps every pixel in the token.

- :func:`fit_patch`: the patch side whose token count per frame is nearest the budget (in ratio), among the sides
  that tile the (latent) frame exactly.
- :func:`size_from_data`: ``cfg`` with ``model.patch_size`` so chosen (unless the user set it).
- :func:`cost`: what a train step of ``cfg`` will cost here (tokens, FLOPs from the lowered step, seconds from this
  machine's measured matmul rate, memory from ``memory.py``), printed by ``sc3 train`` before anything compiles.
"""
from __future__ import annotations

import dataclasses
import math
import time

from sc3_jax.core.errors import UserError


def fit_patch(image_size: tuple[int, int], num_views: int, frame_tokens: int, downsample: int = 1) -> int:
    """The patch side (in latent cells when ``downsample`` > 1) that tiles ``image_size / downsample`` exactly and
    whose tokens per frame over ``num_views`` views are nearest ``frame_tokens`` (ties: more tokens, more detail)."""
    if frame_tokens < 1 or num_views < 1:
        raise UserError(f"model.frame_tokens={frame_tokens} for {num_views} view(s): both must be at least 1")
    h, w = image_size[0] // downsample, image_size[1] // downsample
    sides = [p for p in range(1, math.gcd(h, w) + 1) if h % p == 0 and w % p == 0]

    def tokens(p: int) -> int:
        return num_views * (h // p) * (w // p)
    return min(sides, key=lambda p: (abs(math.log(tokens(p) / frame_tokens)), -tokens(p)))


def size_from_data(cfg, declared, explicit=frozenset()) -> tuple:
    """(``cfg`` sized, a line saying what changed or None). ``cfg``: the config with the data's shape filled
    (``data.shape.shape_from_dataset``); ``declared``: the same config at the shape it was written for (its own
    views and image size), whose train step is the cost the name stands for.

    1. ``model.patch_size`` fitted to ``model.frame_tokens`` on the data's image size and views.
    2. ``data.batch_size`` halved while a step costs over ``MAX_COST`` x the declared step's FLOPs (a larger
       patch packs more pixels into each token, so equal tokens are not yet equal cost).
    Neither where the user named the field, nor for a config without a budget."""
    m = cfg.model
    if m.frame_tokens is None:
        return cfg, None
    notes = []
    if "model.patch_size" not in explicit:
        size, views, down = tuple(cfg.data.image_size), len(cfg.data.views), _downsample(m)
        patch = fit_patch(size, views, m.frame_tokens, down)
        tokens = views * (size[0] // down // patch) * (size[1] // down // patch)
        if tokens > 8 * m.frame_tokens:  # sides with few common divisors (97 x 128): no patch comes near the budget
            raise UserError(f"data.image_size {size[0]}x{size[1]} tiles only into {tokens} tokens a frame near "
                            f"model.frame_tokens={m.frame_tokens} (patch {patch}): import the data at a size whose "
                            f"sides share divisors (sc3 data import-lerobot --image-size H W, e.g. multiples of 16), "
                            "or name --model.patch-size")
        if patch != m.patch_size:
            notes.append(f"patch {m.patch_size} -> {patch} ({m.frame_tokens} tokens a frame wanted)")
        cfg = dataclasses.replace(cfg, model=dataclasses.replace(m, patch_size=patch))
    if "data.batch_size" not in explicit:
        budget = step_flops(declared)
        batch = cfg.data.batch_size
        per_sample = step_flops(cfg) / batch  # a step's FLOPs grow with the batch, sample by sample
        while batch % 2 == 0 and batch > 1 and per_sample * batch > MAX_COST * budget:
            batch //= 2
        if batch != cfg.data.batch_size:
            notes.append(f"batch {cfg.data.batch_size} -> {batch} (a step of --config {cfg.name} costs "
                         f"{budget / 1e9:.0f} GFLOP on the shape it was written for)")
        cfg = _batch(cfg, batch)
    return cfg, ("sized from the data: " + "; ".join(notes)) if notes else None


MAX_COST = 1.5


def _batch(cfg, batch: int):
    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, batch_size=batch))


def _downsample(m) -> int:
    """Pixels per latent cell of the config's tokenizer (1: pixel patches)."""
    if m.tokenizer == "pixel":
        return 1
    if m.tokenizer == "conv_ae":
        from sc3_jax.model.tokenizer import make_tokenizer
        return make_tokenizer(m).cfg.downsample
    return 8  # the Wan VAEs: 8x in space


def matmul_rate(seconds: float = 0.2) -> float:
    """FLOP/s of a float32 1024 x 1024 matmul on this machine's first device (measured now, ~0.2 s): the scale
    of the step-time estimate."""
    import jax
    import jax.numpy as jnp

    n = 1024
    a = jnp.ones((n, n), jnp.float32)
    f = jax.jit(lambda x: x @ x)
    f(a).block_until_ready()
    reps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        f(a).block_until_ready()
        reps += 1
    return 2 * n ** 3 * reps / (time.perf_counter() - t0)


# a train step runs at about this share of the machine's matmul rate (`tiny` on two 96x128 views on the 2-core CPU:
# 15 GFLOP a step at 5.6 steps/s against ~430 GFLOP/s of matmul, 0.2; bench/first_run.py prints estimate and truth)
STEP_EFFICIENCY = 0.2


def step_flops(cfg) -> float:
    """A train step's FLOPs from the lowered step at one and two layers, extrapolated per layer to the config's depth:
    every layer costs the same, and lowering a deep model unrolled (what XLA's count needs) takes minutes at every
    `sc3 train` start."""
    from sc3_jax.train import flops
    from sc3_jax.train.distill import teacher_config

    teacher_config(cfg)  # a distillation teacher of another model is refused here, at the config's own depth
    at = {d: flops.train_step_flops(dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, depth=d)),
                                    check_teacher=False)
          for d in sorted({1, min(2, cfg.model.depth)})}
    per_layer = at[2] - at[1] if 2 in at else 0.0
    return at[1] + per_layer * (cfg.model.depth - 1)


def cost(cfg, num_devices: int = 1) -> dict:
    """What one train step of ``cfg`` costs: tokens per frame and per sample, GFLOPs (the lowered step), the
    estimated seconds here, and the estimated memory (train state + activations, ``memory.py``)."""
    from sc3_jax.train.memory import activation_estimate, state_bytes
    from sc3_jax.model import sharding
    from sc3_jax.model import tokenizer

    rows, cols = tokenizer.make_tokenizer(cfg.model).grid(tuple(cfg.data.image_size))
    names = sharding.mesh_axes(cfg.mesh)
    mesh_cfg = dataclasses.replace(cfg.mesh, **dict(zip(names, sharding.mesh_shape(cfg.mesh, num_devices))))
    flops = step_flops(cfg)
    memory = sum(state_bytes(cfg, mesh_cfg).values()) + activation_estimate(cfg, mesh_cfg)
    return {"views": len(cfg.data.views), "frame_tokens": len(cfg.data.views) * rows * cols,
            "sample_tokens": tokenizer.tokens_per_sample(cfg), "batch": cfg.data.batch_size,
            "patch_size": cfg.model.patch_size, "gflops": flops / 1e9,
            "seconds": flops / (matmul_rate() * STEP_EFFICIENCY * num_devices), "memory_gb": memory / 1e9}


def describe(c: dict) -> str:
    """The lines ``sc3 train`` prints before compiling, with how to cut the cost."""
    return (f"cost: {c['frame_tokens']} tokens a frame over {c['views']} view(s) (patch {c['patch_size']}), "
            f"{c['sample_tokens']} a sample, batch {c['batch']}: {c['gflops']:.1f} GFLOP a step, about "
            f"{c['seconds']:.2g} s a step here and {c['memory_gb']:.1f} GB (estimates)\n"
            "  to cut it: --model.frame-tokens N (fewer tokens a frame), --batch N, --data.views V ... "
            "(fewer cameras), --data.future-frames N")
