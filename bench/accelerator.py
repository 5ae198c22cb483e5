"""Train-step MFU and closed-loop rollout chunk time on whatever backend is present.

    python bench/accelerator.py [--repeats 3] [--depth 4] [--size auto|tiny|mid] [--compare]

* Train step: on a GPU / TPU a mid-size model (dim 1024, 16 layers, ~250M parameters, bf16, 5,764 tokens per
  sample, memory-efficient attention ("fused": cuDNN where it applies, else blockwise), remat "dots"); on a CPU a
  tiny one (and it says so). MFU = XLA cost-analysis FLOPs of the step (``flops.train_step_flops``: the same
  program with the layer scan unrolled, lowered) / step time / peak. The peak is the vendor dense-BF16 figure of
  the device (``plan.DEVICES``, matched by device kind); on a CPU, or an unknown device, the measured rate of a
  plain jitted square matmul stands in for it (printed as such).
* Rollout chunk: one closed-loop chunk of one episode (``rollout.Rollout.run``: observe, forward-dynamics
  sampling of l' frames, inverse-dynamics sampling of their actions, policy) of the ``paper`` config (3 views,
  480x640, K = 4, l' = 24, S = 10 Euler steps, context caching) at reduced depth (``--depth``, random weights);
  the time scaled to the full 32 layers is printed next to the paper's 2.3 s per chunk on one GB200. On a CPU the
  chunk keeps the paper's proportions at a tiny size (64x64 frames, dim 64, 1 layer). ``--compare`` also times,
  interleaved in the same process, the chunk as before the context cache (the inverse sampler recomputing the context's
  keys/values instead of reusing the forward sampler's; bench/chunk_account.py counts both).

Last line: ``accelerator <device>: train_mfu=<x> chunk_s=<y>`` (chunk_s as measured, at the reduced size)."""
from __future__ import annotations

import argparse
import math
import time
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.model import flow, sharding
from sc3_jax.train import plan, train
from sc3_jax.train.flops import train_step_flops
from sc3_jax.rollout import rollout
from sc3_jax.core.config import MeshConfig, load_config, replace
from sc3_jax.data.action_space import DELTA_EE
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.model import dit
from sc3_jax.model import tokenizer
from sc3_jax.model.tokenizer import make_tokenizer
from sc3_jax.policies import simple

PAPER_FPS = 20.0  # the paper config's data (the bussing benchmark's episodes): the rollout's frame stride

PAPER_SECONDS_PER_CHUNK = 2.3  # one GB200 (paper)
KINDS = {"h100": "h100", "h200": "h200", "gb200": "gb200", "b200": "gb200", "v5p": "v5p"}  # device_kind -> DEVICES


def device_peak(device) -> tuple[float | None, str]:
    """(peak dense-BF16 FLOP/s from plan.DEVICES, name) for a known accelerator, else (None, device kind)."""
    kind = device.device_kind.lower().replace(" ", "")
    for key, name in KINDS.items():
        if key in kind:
            return plan.DEVICES[name][0], name
    return None, device.device_kind


def matmul_flops_per_s(n: int, dtype, repeats: int) -> float:
    a = jax.random.normal(jax.random.key(0), (n, n), dtype)
    b = jax.random.normal(jax.random.key(1), (n, n), dtype)
    f = jax.jit(lambda a, b: a @ b)
    return 2 * n ** 3 / _best(lambda: f(a, b), repeats)


def _best(fn, repeats: int, warm: bool = True) -> float:
    if warm:
        jax.block_until_ready(fn())  # compile + warm up
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best


def train_config(size: str):
    base = replace(load_config("tiny"), mesh=MeshConfig(1, 1, 1))
    if size == "tiny":
        return replace(base, model=dict(dim=64, depth=2, num_heads=2, num_kv_heads=1, head_dim=32, mlp_dim=128,
                                        attention_impl="blockwise", attention_block=128),
                       data=dict(image_size=(32, 32), batch_size=2))
    return replace(base, model=dict(dim=1024, depth=16, num_heads=16, num_kv_heads=8, head_dim=64, mlp_dim=4096,
                                    rope_axes_dim=(12, 10, 10), patch_size=16, dtype="bfloat16", remat="dots",
                                    attention_impl="fused", action_reads_frames=False, anchor_conditioning=False),
                   data=dict(image_size=(256, 320), batch_size=4))


def train_step_seconds(cfg, repeats: int) -> float:
    mesh = sharding.make_mesh(cfg.mesh, jax.devices()[:1])
    step, _ = train.compile_train_step(cfg, mesh)
    state = train.create_state(cfg, mesh)
    shapes = train.batch_shapes(cfg)
    rng = np.random.default_rng(0)
    batch = sharding.global_batch(mesh, {
        "frames": rng.integers(0, 256, shapes["frames"].shape, dtype=np.uint8),
        "actions": rng.normal(size=shapes["actions"].shape).astype(np.float32),
        "stride": np.ones(shapes["stride"].shape, np.int32)})
    compiled = step.lower(state, batch).compile()
    box = [state]

    def run():
        box[0], metrics = compiled(box[0], batch)  # the state is donated: keep the new one
        return metrics["loss"]
    return _best(run, repeats)


def chunk_config(size: str, depth: int):
    paper = load_config("paper")
    if size == "tiny":
        return replace(paper, model=dict(dim=64, depth=1, num_heads=2, num_kv_heads=1, head_dim=32, mlp_dim=128,
                                         rope_axes_dim=(6, 5, 5), patch_size=16, dtype="float32",
                                         attention_impl="blockwise", attention_block=256),
                       data=dict(image_size=(64, 64)), mesh=MeshConfig(1, 1, 1))
    return replace(paper, model=dict(depth=depth, attention_impl="fused"), mesh=MeshConfig(1, 1, 1))


def chunk_seconds(cfg, repeats: int, compare: bool = False):
    """Wall time of one closed-loop chunk of one episode (Rollout.run with num_chunks=1). ``compare``: (today's,
    before the context cache's) best times, their runs interleaved; the latter traced with the context's keys/values not
    shared between the two samplers (``flow.shares_context`` False: each sampler computes its own, as before)."""
    mesh = sharding.make_mesh(cfg.mesh, jax.devices()[:1])
    # the paper config's robot: the bussing benchmark's 7-D delta_ee actions at 20 fps
    stats = NormStats(np.zeros(7, np.float32), np.full(7, 0.01, np.float32), action_space=DELTA_EE)
    ro = rollout.Rollout(cfg, stats, mesh=mesh, data_fps=PAPER_FPS, num_chunks=1)
    run = _chunk_runner(cfg, ro)
    if not compare:
        return _best(run, repeats)
    jax.block_until_ready(run())  # traced and compiled before the old program replaces the cached one
    rollout._compiled.cache_clear()
    old = _chunk_runner(cfg, rollout.Rollout(cfg, stats, mesh=mesh, data_fps=PAPER_FPS, num_chunks=1))
    with mock.patch.object(flow, "shares_context", lambda *a: False):
        jax.block_until_ready(old())
    best = [math.inf, math.inf]
    for _ in range(repeats):
        for i, fn in enumerate((run, old)):
            best[i] = min(best[i], _best(fn, 1, warm=False))
    return tuple(best)


def _chunk_runner(cfg, ro):
    tok = make_tokenizer(cfg.model)
    params = dit.init_params(cfg.model, tok.token_dim, jax.random.key(0), tok.grid(cfg.data.image_size))
    V, K, (H, W) = len(cfg.data.views), cfg.data.context_frames, cfg.data.image_size
    rng = np.random.default_rng(0)
    ics = rollout.InitialConditions(rng.integers(0, 256, (1, V, K, H, W, 3), dtype=np.uint8),
                                    np.zeros((1, 7), np.float32), np.zeros(1, np.int32))
    policy = simple.linear_policy(jax.random.key(2), V, chunk=cfg.rollout.policy_chunk)
    keys = rollout.episode_keys(0, 1)
    return lambda: ro.run(params, policy, ics, keys, math.inf)["u"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--depth", type=int, default=4, help="layers of the paper config for the chunk timing")
    ap.add_argument("--compare", action="store_true", help="also time the chunk without the context cache, interleaved")
    ap.add_argument("--size", choices=("auto", "tiny", "mid"), default="auto",
                    help="auto: mid-size on an accelerator, tiny on a CPU")
    args = ap.parse_args(argv)
    dev = jax.devices()[0]
    backend = jax.default_backend()
    size = args.size if args.size != "auto" else ("tiny" if backend == "cpu" else "mid")
    peak, name = device_peak(dev)
    if peak is None:  # CPU or an unknown chip: the measured matmul rate stands in for the peak
        dtype = jnp.float32 if backend == "cpu" else jnp.bfloat16
        peak = matmul_flops_per_s(1024 if backend == "cpu" else 8192, dtype, args.repeats)
        peak_note = f"measured {jnp.dtype(dtype).name} matmul rate {peak / 1e12:.3g} TFLOP/s (no vendor peak)"
    else:
        peak_note = f"vendor dense-BF16 peak {peak / 1e12:.0f} TFLOP/s"
    if size == "tiny":
        print(f"{backend} backend ({dev.device_kind}): TINY sizes (a CPU cannot run the mid-size model); the "
              "numbers say only that the bench runs")

    cfg = train_config(size)
    flops = train_step_flops(cfg)
    sec = train_step_seconds(cfg, args.repeats)
    n_params = dit.count_params(jax.eval_shape(lambda: train.init_state(cfg)["params"]))
    mfu = flops / sec / peak
    print(f"train step ({size}: {n_params / 1e6:.1f}M params, {tokenizer.tokens_per_sample(cfg)} tokens/sample x "
          f"batch {cfg.data.batch_size}, {cfg.model.dtype}, attention {cfg.model.attention_impl}, remat "
          f"{cfg.model.remat}): {sec * 1e3:.1f} ms, {flops / 1e9:.1f} GFLOP/step (lowered XLA cost analysis), "
          f"{flops / sec / 1e12:.3g} TFLOP/s = MFU {mfu:.3f} of the {peak_note}", flush=True)

    ccfg = chunk_config(size, args.depth)
    csec = chunk_seconds(ccfg, args.repeats, args.compare)
    if args.compare:
        csec, before = csec
        print(f"rollout chunk before the context cache (the inverse sampler re-encoding the context), interleaved with "
              f"today's: {before:.3f} s against {csec:.3f} s", flush=True)
    m = ccfg.model
    line = (f"rollout chunk ({size}: depth {m.depth}, dim {m.dim}, {tokenizer.tokens_per_sample(ccfg)} tokens, "
            f"K={ccfg.data.context_frames} l'={ccfg.data.future_frames}, S={ccfg.sample.steps}, FD+ID, cached "
            f"context, 1 episode): {csec:.3f} s")
    if size != "tiny":
        full = csec * load_config("paper").model.depth / m.depth
        line += (f"; x {load_config('paper').model.depth}/{m.depth} layers = {full:.2f} s at full depth "
                 f"(paper: {PAPER_SECONDS_PER_CHUNK} s per chunk on one GB200)")
    print(line, flush=True)
    print(f"accelerator {name}: train_mfu={mfu:.3f} chunk_s={csec:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
