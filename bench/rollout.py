"""Rollout engine benchmark, measured side by side in one run (tiny random-parameter models on this CPU):

  (i)   scan vs host loop: time per chunk of ``Rollout.run`` (whole episode in one jitted lax.scan, JAX policy) and
        ``Rollout.run_host`` (the same jitted observe / model-step pieces driven from Python, the policy on the host);
  (ii)  cached vs uncached context keys/values (``context_attention="causal"``), time per chunk at the paper's
        proportions (K = 4 context frames, l' = 24 predicted, l = 16 kept, policy chunk 25, 3 views);
  (iii) analytic FLOPs of one 24-frame chunk (FD + ID sampling, S Euler steps each) at paper scale, the rate the
        paper's 2.3 s per chunk on one GB200 implies, and the fraction of it this CPU reaches (measured on (ii)).

    nice python bench/rollout.py [--steps 10] [--repeats 3]

Last line: ``rollout: scan_over_host=<x> cached_speedup=<y> paper_chunk_gflops=<z>`` with x = host-loop time / scan
time, y = uncached time / cached time, z = analytic GFLOPs per paper chunk (with the context cache)."""
from __future__ import annotations

import argparse
import math
import time

import jax
import numpy as np

from sc3_jax.rollout import rollout
from sc3_jax.core.config import MeshConfig, load_config, replace
from sc3_jax.data.action_space import DELTA_EE
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.model import dit
from sc3_jax.model.tokenizer import make_tokenizer
from sc3_jax.policies import simple
from sc3_jax.policies.base import as_host

PAPER_FPS = 20.0  # the paper config's data (the bussing benchmark's episodes): the rollout's frame stride

PAPER_SECONDS_PER_CHUNK = 2.3  # one GB200 (paper)
GB200_BF16_DENSE = 2.5e15  # FLOP/s, one Blackwell GPU of a GB200, dense BF16 (vendor figure; assumption)


# -- analytic FLOPs ---------------------------------------------------------------------------------------------
def forward_flops(cfg, n_q: int, n_k: int, token_dim: int) -> float:
    """Matmul + attention FLOPs of one DiT pass of ``n_q`` tokens attending to ``n_k`` keys (2 FLOPs per MAC)."""
    m = cfg.model
    d, hq, hkv, hd = m.dim, m.num_heads, m.num_kv_heads, m.head_dim
    per_token = 2 * d * hq * hd + 2 * 2 * d * hkv * hd + 2 * hq * hd * d + 3 * 2 * d * m.mlp_dim
    attn = 2 * 2 * n_q * n_k * hq * hd  # scores + weighted values
    io = 2 * 2 * n_q * token_dim * d  # proj_in + proj_out
    return m.depth * (n_q * per_token + attn) + io


def chunk_flops(cfg, cached: bool, latent_frames: tuple[int, int] | None = None) -> float:
    """One chunk = FD sampling + ID sampling, S Euler steps each. Uncached: every step runs all tokens. Cached
    (context_attention="causal"): FD encodes the context once, then each step runs the future frames and the actions
    against all keys; ID encodes every frame once, then each step runs only the l' action tokens."""
    tok = make_tokenizer(cfg.model)
    rows, cols = tok.grid(cfg.data.image_size)
    P, V, K, T = rows * cols, len(cfg.data.views), cfg.data.context_frames, cfg.data.future_frames
    Kv, Tv = latent_frames or (K, T)  # video frames as tokenised (a temporally compressing VAE has fewer)
    S, td = cfg.sample.steps, tok.token_dim
    n_ctx, n_video = V * Kv * P, V * (Kv + Tv) * P
    n_all = n_video + T
    if not cached:
        return 2 * S * forward_flops(cfg, n_all, n_all, td)
    fd = forward_flops(cfg, n_ctx, n_ctx, td) + S * forward_flops(cfg, n_all - n_ctx, n_all, td)
    idm = forward_flops(cfg, n_video, n_video, td) + S * forward_flops(cfg, T, n_all, td)
    return fd + idm


# -- timing -----------------------------------------------------------------------------------------------------
def _setup(cfg, num_chunks, batch, cache=True):
    mesh = jax.make_mesh((1, 1, 1), ("data", "fsdp", "tensor"), axis_types=(jax.sharding.AxisType.Auto,) * 3,
                         devices=jax.devices()[:1])
    # the paper config's robot: the bussing benchmark's 7-D delta_ee actions at 20 fps
    stats = NormStats(np.zeros(7, np.float32), np.full(7, 0.01, np.float32), action_space=DELTA_EE)
    ro = rollout.Rollout(cfg, stats, mesh=mesh, data_fps=PAPER_FPS, num_chunks=num_chunks, cache=cache)
    tok = make_tokenizer(cfg.model)
    params = dit.init_params(cfg.model, tok.token_dim, jax.random.key(0), tok.grid(cfg.data.image_size))
    params = jax.tree.map(lambda x: x + 0.02 * jax.random.normal(jax.random.key(1), x.shape), params)
    V, K, (H, W) = len(cfg.data.views), cfg.data.context_frames, cfg.data.image_size
    rng = np.random.default_rng(0)
    ics = rollout.InitialConditions(rng.integers(0, 256, (batch, V, K, H, W, 3), dtype=np.uint8),
                                    np.zeros((batch, 7), np.float32), np.zeros(batch, np.int32))
    policy = simple.linear_policy(jax.random.key(2), V, chunk=cfg.rollout.policy_chunk)
    return ro, params, ics, rollout.episode_keys(0, batch), policy


def _interleaved(fns: dict, repeats: int) -> dict:
    """Best wall time of each function; rounds alternate between them so all see the same machine load."""
    for fn in fns.values():
        fn()  # compile + warm up
    best = {k: math.inf for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            best[k] = min(best[k], time.perf_counter() - t0)
    return best


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--steps", type=int, default=10, help="Euler steps per sampler call (config default 10)")
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    base = load_config("tiny")
    small = dict(dim=64, depth=2, num_heads=2, num_kv_heads=1, mlp_dim=128, head_dim=32)

    # (i) scan vs host loop
    cfg1 = replace(base, model=small, data=dict(image_size=(16, 16), context_frames=2, future_frames=4),
                   rollout=dict(policy_chunk=5, keep_frames=3), sample=dict(steps=args.steps),
                   mesh=MeshConfig(1, 1, 1))
    n1 = 4
    ro, params, ics, keys, policy = _setup(cfg1, n1, batch=2)
    host_policy = as_host(policy)
    t = _interleaved({"scan": lambda: ro.run(params, policy, ics, keys, math.inf),
                      "host": lambda: ro.run_host(params, host_policy, ics, keys, math.inf)}, args.repeats)
    t_scan, t_host = t["scan"] / n1, t["host"] / n1
    a, b = ro.run(params, policy, ics, keys, math.inf), ro.run_host(params, host_policy, ics, keys, math.inf)
    print(f"(i)   scan {t_scan * 1e3:.1f} ms/chunk   host loop {t_host * 1e3:.1f} ms/chunk   "
          f"(2 episodes, 16x16, K=2 l'=4 l=3, S={args.steps}; "
          f"max |dU| scan vs host {np.abs(a['u'] - b['u']).max():.1e})")

    # (ii) cached vs uncached at the paper's proportions
    cfg2 = replace(base, model=dict(dim=128, depth=2, num_heads=4, num_kv_heads=2, head_dim=32, mlp_dim=384,
                                    context_attention="causal"),
                   data=dict(image_size=(32, 32), context_frames=4, future_frames=24),
                   rollout=dict(policy_chunk=25, keep_frames=16), sample=dict(steps=args.steps),
                   mesh=MeshConfig(1, 1, 1))
    n2 = 2
    runs, flops = {}, {}
    for cached in (True, False):
        ro, params, ics, keys, policy = _setup(cfg2, n2, batch=1, cache=cached)
        runs[cached] = (lambda ro=ro, params=params, ics=ics, keys=keys, policy=policy:
                        ro.run(params, policy, ics, keys, math.inf))
        flops[cached] = chunk_flops(cfg2, cached)
    times = {k: v / n2 for k, v in _interleaved(runs, args.repeats).items()}
    speedup = times[False] / times[True]
    cpu_rate = flops[True] / times[True]
    print(f"(ii)  cached {times[True] * 1e3:.1f} ms/chunk   uncached {times[False] * 1e3:.1f} ms/chunk   "
          f"speedup {speedup:.2f}x (analytic FLOP ratio {flops[False] / flops[True]:.2f}x; K=4 l'=24 l=16, 3 views "
          f"32x32, dim 128 depth 2, S={args.steps}); CPU rate {cpu_rate / 1e9:.1f} GFLOP/s")

    # (iii) paper scale, analytic
    paper = load_config("paper")
    paper = replace(paper, sample=dict(steps=args.steps))
    pf_c, pf_u = chunk_flops(paper, True), chunk_flops(paper, False)
    implied = pf_c / PAPER_SECONDS_PER_CHUNK
    tok = make_tokenizer(paper.model)
    rows, cols = tok.grid(paper.data.image_size)
    print(f"(iii) paper scale ({rows}x{cols} tokens/frame, 3 views, K=4 l'=24, S={args.steps}, FD+ID): "
          f"{pf_c / 1e9:,.0f} GFLOP/chunk cached ({pf_u / 1e9:,.0f} uncached). 2.3 s/chunk on one GB200 implies "
          f"{implied / 1e12:,.0f} TFLOP/s = {implied / GB200_BF16_DENSE:.0%} of {GB200_BF16_DENSE / 1e15:.1f} PFLOP/s "
          f"dense BF16. This CPU at {cpu_rate / 1e9:.1f} GFLOP/s is {cpu_rate / implied:.1e} of that rate: "
          f"{pf_c / cpu_rate / 3600:,.1f} h per paper chunk.")
    lat = chunk_flops(paper, True, latent_frames=(1, 6))
    print(f"      with the Wan VAE's 4x temporal compression (context 1 + future 6 latent frames, 24 action tokens): "
          f"{lat / 1e9:,.0f} GFLOP/chunk -> {lat / PAPER_SECONDS_PER_CHUNK / GB200_BF16_DENSE:.0%} of the GB200 peak "
          f"in 2.3 s; cached/uncached FLOP ratio at paper proportions {pf_u / pf_c:.2f}x")
    print(f"rollout: scan_over_host={t_host / t_scan:.2f} cached_speedup={speedup:.2f} "
          f"paper_chunk_gflops={pf_c / 1e9:.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
